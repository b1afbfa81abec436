"""What every learner's run shares, written once: the envs, the counters, the logger and progress bar, the
evaluation and checkpoint schedule, the one resume path and the results.

A learner's ``train`` reads::

    @learner                                              # checks cfg, sets the torch threads
    def train(cfg, out, resume=False, progress=True):
        run = Run("sac", cfg, out, resume, progress)      # seeds, resolves the params once, builds, resets the envs
        ...networks, optimizers, buffer...
        ck = run.start(actor=actor, critic=critic, ...)   # --resume: loads them, the env, counters, RNG; logger
        while run.step < cfg.run.total_steps:
            ...act: next_obs, reward, term, trunc, info, final_obs = run.env.step(action)
            run.count(info, term, trunc)
            ...learn
            run.evaluate_if_due(lambda: run.evaluate(policy))
            run.checkpoint_if_due(lambda: {"actor": actor, ...})
        return run.finish(policy, extra={...})

Everything with a ``state_dict`` is saved by it; other values as they are.
"""
from __future__ import annotations

import functools
import sys
import time
from pathlib import Path
from typing import Any, Callable

import torch
from tqdm import tqdm

from agents.common.checkpoints import (CHECKPOINT, load_checkpoint, load_weights, rng_state, save_checkpoint,
                                       seed_everything, set_rng_state, torch_threads)
from agents.common.config import to_dict
from agents.common.envs import make_env
from agents.common.evaluation import episode_records, eval_row, evaluate, evaluate_heldout, heldout_envs, write_results
from agents.common.logs import EpisodeStats, Logger, fmt_postfix
from agents.common.rollout import PolicyRollouts, check_acts_by_rollouts
from diffdlo.utils.files import check_fresh_out, out_lock
from diffdlo.utils.signals import Interrupted, StopRequest, stop_at_boundary

_stop: list[StopRequest] = []      # the running learner's stop request (SIGINT/SIGTERM/SIGHUP), set by @learner


def learner(train: Callable) -> Callable:
    """A learner's ``train(cfg, out, resume=False, progress=True, overwrite=False)``: the config checked; a fresh run
    refused in a folder that holds an earlier run (unless ``overwrite``: its logs are then replaced); the folder
    locked against a second writer; run with cfg.run.threads torch CPU threads (restored afterwards). A SIGINT,
    SIGTERM or SIGHUP, however the process was started, stops it at the next step boundary with a checkpoint saved
    (``Interrupted``; ``--resume`` continues exactly); a second signal stops it at once."""
    @functools.wraps(train)
    def checked_train(cfg, out: Path | str, resume: bool = False, progress: bool = True,
                      overwrite: bool = False) -> dict[str, Any]:
        cfg.check()
        if not resume:
            check_fresh_out(out, overwrite, "an earlier run")
        with out_lock(out), torch_threads(cfg.run.threads), stop_at_boundary() as request:
            _stop.append(request)
            try:
                return train(cfg, out, resume, progress)
            finally:
                _stop.remove(request)
    return checked_train


class Run:
    """One learner's run: ``cfg.task`` and ``cfg.run`` (agents/common/config.py) made into envs, counters and files."""

    def __init__(self, algo: str, cfg, out: Path | str, resume: bool, progress: bool):
        self.algo, self.cfg, self.out, self.resume = algo, cfg, Path(out), resume
        self.out.mkdir(parents=True, exist_ok=True)
        task, opts = cfg.task, cfg.run
        self.device = torch.device(opts.device)
        seed_everything(opts.seed)
        self.params = task.cable_params()
        if opts.rollout_candidates:
            try:
                check_acts_by_rollouts(algo, task.obs)
            except ValueError as exc:
                raise ValueError(f"rollout_candidates: {exc}") from None
        self.env = make_env(task, opts, self.params, opts.num_envs)
        self.eval_env = make_env(task, opts, self.params, min(opts.eval_episodes, 32))
        self.heldout = heldout_envs(task, opts, self.params)
        self.obs = self.env.reset(seed=opts.seed)
        self.stats = EpisodeStats()
        self.step, self.last_eval, self.last_ckpt, self.wall_before = 0, 0, 0, 0.0
        self.last_success: float | None = None
        self.result: dict[str, Any] | None = None
        self.progress = progress
        self._stoppable_eval = False
        self.logger: Logger | None = None
        self.bar: tqdm | None = None
        self.t0 = time.perf_counter()

    # ------------------------------------------------------------------ start (and resume)
    def start(self, **parts: Any) -> dict[str, Any] | None:
        """Load ``parts`` (name -> object with load_state_dict), the env, the counters and every RNG from the
        checkpoint on --resume, then open the logs and the progress bar. Returns the checkpoint (for a learner's own
        counters), or None on a fresh run."""
        ck = None
        if self.resume:
            ck = load_checkpoint(self.out / CHECKPOINT)
            for name, part in parts.items():
                load_weights(part, ck[name], self.out / CHECKPOINT, name)
            self.env.load_state_dict(ck["env"])
            self.obs = self.env.observe()
            self.stats.buf.extend(ck["episode_stats"])
            self.step, self.last_eval, self.last_ckpt = ck["step"], ck["last_eval"], ck["last_ckpt"]
            self.last_success, self.wall_before = ck["last_success"], ck["wall_s"]
            self.result = ck.get("result")           # the last evaluation (reused when nothing is left to train)
            set_rng_state(ck["rng"])
        self.logger = Logger(self.out, resume_step=self.step if self.resume else None,
                             resume_rows=ck.get("log_rows") if ck else None)
        total = self.cfg.run.total_steps
        self.bar = tqdm(total=total, initial=min(self.step, total), desc=self.algo, disable=not self.progress,
                        dynamic_ncols=True, file=sys.stderr)
        self.t0 = time.perf_counter()
        return ck

    # ------------------------------------------------------------------ the loop's bookkeeping
    def count(self, info: dict[str, torch.Tensor], term: torch.Tensor, trunc: torch.Tensor,
              update_bar: bool = True) -> None:
        """One batched env step taken: its finished episodes recorded, the step counter (and the bar) advanced."""
        done = (term | trunc).cpu()
        if bool(done.any()):
            self.stats.add(info, done)
        self.step += self.cfg.run.num_envs
        if update_bar:
            self.bar.update(self.cfg.run.num_envs)

    def log_rollout(self) -> None:
        if self.stats.buf:
            self.logger.log("rollout", self.step, self.stats.means())

    def evaluate(self, policy: Callable[[Any, bool], torch.Tensor]) -> dict[str, Any]:
        opts = self.cfg.run
        return evaluate(policy, self.eval_env, opts.eval_episodes, seed=opts.eval_seed,
                        check_stop=self._stop_evaluation if self._stoppable_eval else None)

    def evaluate_if_due(self, evaluate_fn: Callable[[], dict[str, Any]],
                        save_first: Callable[[], dict[str, Any]] | None = None) -> None:
        """Every eval_every env steps and at the end of the budget (once): ``evaluate_fn()`` logged as an eval row.
        ``save_first`` (the parts, as for ``checkpoint_if_due``): a checkpoint just before, for an evaluation that
        takes minutes (one that plans every move); ``run.evaluate`` then stops at a move on a signal, and --resume
        evaluates again from that checkpoint, as the uninterrupted run did. It does not move the checkpoint
        schedule."""
        opts = self.cfg.run
        if (self.step - self.last_eval >= opts.eval_every
                or (self.step >= opts.total_steps and self.last_eval < self.step)):
            if save_first is not None:
                self.save(save_first())
            self._stoppable_eval = save_first is not None
            try:
                self.result = evaluate_fn()
            finally:
                self._stoppable_eval = False
            self.last_eval = self.step
            self.last_success = self.result["success_rate"]
            self.logger.log("eval", self.step, eval_row(self.result))
            self.bar.set_postfix(fmt_postfix(self.last_success))

    def checkpoint_if_due(self, parts_fn: Callable[[], dict[str, Any]]) -> None:
        """Every checkpoint_every env steps and at the end of the budget (once): the learner's parts and the run's
        state in one atomic file. Asked to stop (a signal, see ``learner``): a checkpoint now, then ``Interrupted``."""
        opts = self.cfg.run
        due = (self.step - self.last_ckpt >= opts.checkpoint_every
               or (self.step >= opts.total_steps and self.last_ckpt < self.step))
        if due:
            self.last_ckpt = self.step
        if due or self.stop_requested():
            self.save(parts_fn())
        self._interrupt_if_stopped("")

    def stop_if_requested(self, parts_fn: Callable[[], dict[str, Any]]) -> None:
        """Within a step (e.g. between a phase's updates): asked to stop, a checkpoint now (``parts_fn()`` must hold
        whatever the learner needs to finish the step on --resume), then ``Interrupted``. Does not move the
        checkpoint schedule."""
        if self.stop_requested():
            self.save(parts_fn())
            self._interrupt_if_stopped(", within the step", "checkpoint saved (--resume finishes the step)")

    def stop_requested(self) -> str | None:
        """The signal's name once one asked the run to stop, else None."""
        return _stop[-1].signal if _stop else None

    def _interrupt_if_stopped(self, where: str, saved: str = "checkpoint saved") -> None:
        stop = self.stop_requested()
        if stop:
            self.bar.close()
            self.logger.close()
            raise Interrupted(stop, self.step, f"{self.algo}: stopped by {stop} at env step {self.step}{where}; "
                                               f"{saved}: continue with --out {self.out} --resume")

    def _stop_heldout(self) -> None:
        self._interrupt_if_stopped(", in the held-out evaluation after training", "the last checkpoint holds the "
                                   "trained run (--resume evaluates again and writes results.json)")

    def _stop_evaluation(self) -> None:
        self._interrupt_if_stopped(", in an evaluation", "the checkpoint saved before it evaluates again")

    def save(self, parts: dict[str, Any]) -> None:
        state = {k: v.state_dict() if hasattr(v, "state_dict") else v for k, v in parts.items()}
        save_checkpoint(self.out / CHECKPOINT, {
            "algo": self.algo, "config": to_dict(self.cfg), **state, "env": self.env.state_dict(),
            "episode_stats": list(self.stats.buf), "step": self.step, "last_eval": self.last_eval,
            "last_ckpt": self.last_ckpt, "last_success": self.last_success, "result": self.result,
            "log_rows": dict(self.logger.rows),
            "wall_s": self.wall_s(), "rng": rng_state()})

    def act_by_rollouts(self, policy: Callable[[Any, bool], torch.Tensor], extra: dict[str, Any] | None
                        ) -> tuple[PolicyRollouts, dict[str, Any]]:
        """The final evaluation again, acting by policy rollouts (agents/common/rollout.py): it becomes the run's result;
        the policy's own evaluation is kept in results.json as "policy_alone", the rollouts' cost on the task's
        episodes (not the held-out ones') as "sim_evals_per_move"."""
        opts = self.cfg.run
        acting = PolicyRollouts(policy, self.cfg.task.env_options(self.params), opts.rollout_candidates,
                                opts.rollout_moves, seed=opts.eval_seed,
                                env_device=opts.env_device or opts.device, learner_device=self.device)
        alone = {**eval_row(self.result), "episodes": episode_records(self.result["episodes"])}
        self.result = self.evaluate(acting)
        return acting, {**(extra or {}), "policy_alone": alone, **acting.stats()}   # the stats of this evaluation

    def wall_s(self) -> float:
        """Training and its evaluations so far, over every resumed part of the run."""
        return self.wall_before + time.perf_counter() - self.t0

    # ------------------------------------------------------------------ the end
    def finish(self, policy: Callable[[Any, bool], torch.Tensor] | None, extra: dict[str, Any] | None = None,
               evaluate_fn: Callable[[], dict[str, Any]] | None = None,
               policy_for: Callable[[Any], Callable] | None = None,
               before_heldout: Callable[[], None] | None = None) -> dict[str, Any]:
        """Close the bar and logs, evaluate on the held-out targets (not counted in wall_s) and write results.json
        and its picture. A run resumed at its end trains nothing and reuses its saved last evaluation, so it adds no
        log rows; ``evaluate_fn`` (default: ``evaluate(policy)``) only serves a checkpoint that holds none. A signal
        stops the held-out evaluation at a move (``Interrupted``): the last checkpoint, saved at the end of the budget,
        holds the trained run, and --resume evaluates it again."""
        self.bar.close()
        if self.result is None:
            self.result = evaluate_fn() if evaluate_fn is not None else self.evaluate(policy)
        self.logger.close()
        wall = self.wall_s()
        if before_heldout is not None:
            before_heldout()
        if self.cfg.run.rollout_candidates and policy is not None:
            policy, extra = self.act_by_rollouts(policy, extra)
        held = evaluate_heldout(policy, self.heldout, self.cfg.run, policy_for=policy_for,
                                check_stop=self._stop_heldout)
        return write_results(self.out, self.algo, self.cfg.task, self.cfg.run.seed, self.result, self.step, wall,
                             heldout=held, extra=extra)
