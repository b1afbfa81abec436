"""Evaluate a trained run and watch it: its checkpoint's policy, deterministic, over full episodes.

    python -m agents.tools.evaluate runs/sac                              # the run's task, its eval episodes and seed
    python -m agents.tools.evaluate runs/sac --target arc_file.npy --episodes 50 --seed 3 --out runs/sac-arc
    python -m agents.tools.evaluate runs/planet --success-tol 0.002 --success-worst-tol 0.01   # at another tolerance

Writes into --out (default RUN_DIR/evaluate-<target>-s<seed>; never over an earlier evaluation unless --overwrite):
``results.json`` (success_rate, the episodes' success/steps/final_error/target_name and their errors after each
move, mean and worst node, the checkpoint's ``step``, as the learners' results.json), ``eval_episodes.png`` (final
shapes against their targets) and ``episodes.gif`` (the first episodes one after another, the rope after every
move, the grasped node starred; --no-gif skips it).
"""
from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
from pathlib import Path
from typing import Any, Sequence

import torch

from agents.common.checkpoints import torch_threads
from agents.common.envs import TrainEnv
from agents.common.evaluation import evaluate, write_results
from agents.tools.policy import load_policy
from agents.common.rollout import PolicyRollouts, check_acts_by_rollouts
from diffdlo.utils.files import check_fresh_out, out_lock
from diffdlo.planar.shapes import TARGET_FAMILIES, TARGET_NAMES, TargetError
from diffdlo.tasks.task import resolve_target, target_label

GIF_FPS = 4            # moves per second
GIF_HOLD = 4           # extra frames showing each episode's end


class UsageError(Exception):
    """A bad flag or value: main prints its one line and returns 2."""


class OneLineParser(argparse.ArgumentParser):
    def error(self, message: str):
        raise UsageError(message)


def count(text: str, least: int = 1) -> int:
    """An integer flag value >= least; anything else is named in the one-line error."""
    try:
        v = int(text)
    except ValueError:
        v = least - 1
    if v < least:
        raise argparse.ArgumentTypeError(f"expected an integer >= {least}, got {text!r}")
    return v


def tolerance(text: str) -> float:
    """A tolerance flag's value: a positive finite number [m]; anything else is named in the one-line error."""
    try:
        v = float(text)
    except ValueError:
        v = float("nan")
    if not (math.isfinite(v) and v > 0):
        raise argparse.ArgumentTypeError(f"expected a positive number [m], got {text!r}")
    return v


def make_parser() -> OneLineParser:
    ap = OneLineParser(prog="python -m agents.tools.evaluate", description=__doc__.split("\n\n")[0])
    ap.add_argument("run_dir", help="a learner's --out folder (its checkpoint.pt), or a checkpoint file")
    ap.add_argument("--episodes", type=count, default=None, help="episodes (default: the run's eval_episodes)")
    ap.add_argument("--target", default=None,
                    help=f"target: one of {list(TARGET_FAMILIES)}, {list(TARGET_NAMES)} or a .npy/.yaml path "
                         "(default: the run's)")
    ap.add_argument("--seed", type=lambda t: count(t, least=0), default=None,
                    help="start seed of the episodes (default: the run's eval_seed)")
    ap.add_argument("--success-tol", type=tolerance, default=None, metavar="M",
                    help="success: mean node error below M [m] (default: the run's)")
    ap.add_argument("--success-worst-tol", type=tolerance, default=None, metavar="M",
                    help="success also needs the worst node's error below M [m] (default: the run's)")
    ap.add_argument("--max-steps", type=count, default=None, metavar="K", help="moves per episode (default: the run's)")
    ap.add_argument("--out", default=None, help="output folder (default: RUN_DIR/evaluate-<target>-s<seed>, with "
                                                "-tol<M>mm[-worst<W>mm] when a tolerance is given)")
    ap.add_argument("--overwrite", action="store_true", help="replace an earlier evaluation in --out")
    ap.add_argument("--no-gif", action="store_true", help="skip episodes.gif")
    ap.add_argument("--gif-episodes", type=count, default=3, help="episodes shown in the GIF (default 3)")
    ap.add_argument("--device", default="cpu", help="torch device of the networks, e.g. cpu (the default) or cuda")
    ap.add_argument("--rollouts", type=lambda t: count(t, least=0), default=0, metavar="C",
                    help="act by policy rollouts through the simulator with C candidate moves (agents/common/rollout.py; "
                         "default 0: the policy alone)")
    ap.add_argument("--rollout-moves", type=lambda t: count(t, least=0), default=20, metavar="K",
                    help="with --rollouts: moves the policy finishes each candidate with (default 20)")
    return ap


# ====================================================================== recording the first episodes
class EpisodeRecorder:
    """A ``BatchedShapeControl`` that also keeps, for its first ``k`` ropes during the first reset's wave, the rope
    after the reset and after every move, and the node each move grasped. Everything else is the core's own
    (``evaluate`` and PlaNet's planner see the env they always do)."""

    def __init__(self, core, k: int):
        self._core, self.k, self.waves = core, min(k, core.num_envs), 0
        self.frames: list[list[torch.Tensor]] = [[] for _ in range(self.k)]
        self.grasped: list[list[int]] = [[] for _ in range(self.k)]

    def __getattr__(self, name: str) -> Any:
        return getattr(self._core, name)

    def _record(self, ropes: list[int]) -> None:
        s = self._core.get_state(generators=False)
        for i in ropes:
            self.frames[i].append(s.pos[i].detach().cpu().clone())
            self.grasped[i].append(int(s.info["node"][i]))

    def reset(self, *args, **kwargs):
        out = self._core.reset(*args, **kwargs)
        self.waves += 1
        if self.waves == 1:
            self._record(list(range(self.k)))
        return out

    def step(self, actions, mask=None, autoreset=None):
        out = self._core.step(actions, mask=mask, autoreset=autoreset)
        if self.waves == 1:
            moved = torch.ones(self.k, dtype=torch.bool) if mask is None else mask.cpu()[:self.k].bool()
            self._record(moved.nonzero().flatten().tolist())
        return out


def write_gif(path: Path, recorder: EpisodeRecorder, targets: torch.Tensor, episodes: list[dict[str, Any]]) -> Path:
    """The recorded episodes one after another, each against its target, its last frame held a moment."""
    from diffdlo.utils.render import save_gif
    frames, frame_targets, titles, grasped = [], [], [], []
    for i, (ropes, nodes) in enumerate(zip(recorder.frames, recorder.grasped)):
        e = episodes[i]
        verdict = f"{'success' if e['success'] else 'fail'}, {e['final_error'] * 100:.2f} cm"
        shown = list(range(len(ropes))) + [len(ropes) - 1] * GIF_HOLD
        for j in shown:
            frames.append(ropes[j])
            frame_targets.append(targets[i])
            grasped.append(nodes[j])
            titles.append(f"episode {i + 1} ({e['target_name']}): " +
                          ("start" if j == 0 else f"move {j}/{len(ropes) - 1}") +
                          (f"\n{verdict}" if j == len(ropes) - 1 else "\n"))
    return save_gif(torch.stack(frames), path, torch.stack(frame_targets), fps=GIF_FPS, title=titles,
                    grasped=grasped)


# ====================================================================== the command
def main(argv: Sequence[str] | None = None) -> int:
    ap = make_parser()
    try:
        args = ap.parse_args(argv)
    except UsageError as exc:
        print(f"{ap.prog}: error: {exc}", file=sys.stderr)
        return 2
    try:
        return evaluate_run(args)
    except (FileNotFoundError, FileExistsError, ValueError, RuntimeError) as exc:
        print(f"{ap.prog}: error: {exc}", file=sys.stderr)
        return 2


def evaluate_run(args: argparse.Namespace) -> int:
    policy = load_policy(args.run_dir, device=args.device)
    cfg = policy.config
    if args.rollouts:
        try:
            check_acts_by_rollouts(policy.algo, cfg.task.obs)
        except ValueError as exc:
            raise ValueError(f"--rollouts: {exc}") from None
    params = cfg.task.cable_params()
    spec = cfg.task.target if args.target is None else args.target
    try:
        resolve_target(spec, params)
    except TargetError as exc:
        raise ValueError(f"--target {args.target!r}: {exc}") from None
    episodes = cfg.run.eval_episodes if args.episodes is None else args.episodes
    seed = cfg.run.eval_seed if args.seed is None else args.seed
    changes = {k: v for k, v in (("success_tol", args.success_tol), ("success_worst_tol", args.success_worst_tol),
                                 ("max_steps", args.max_steps)) if v is not None}
    policy.task(**changes)                  # checked before anything is written
    label = target_label(spec)
    tol = "".join(f"-{name}{v * 1000:g}mm" for name, v in (("tol", args.success_tol),
                                                           ("worst", args.success_worst_tol)) if v is not None)
    out = Path(args.out) if args.out else policy.checkpoint.parent / f"evaluate-{label}-s{seed}{tol}"
    check_fresh_out(out, args.overwrite, "an earlier evaluation")

    with out_lock(out), torch_threads(cfg.run.threads):
        env = policy.make_env(num_envs=min(episodes, 32), target=spec, **changes)
        recorder = EpisodeRecorder(env.core, 0 if args.no_gif else args.gif_episodes)
        env = TrainEnv(recorder, device=env.device)
        acting = policy.batched(env)
        if args.rollouts:
            acting = PolicyRollouts(acting, policy.env_options(**changes), args.rollouts, args.rollout_moves, seed=seed,
                                    env_device=env.core.device, learner_device=env.device)
        t0 = time.perf_counter()
        result = evaluate(acting, env, episodes, seed=seed)
        task = dataclasses.replace(policy.task(**changes), target=spec if isinstance(spec, str) else label)
        write_results(out, policy.algo, task, seed, result, env_steps=policy.step, wall_s=time.perf_counter() - t0,
                      extra={"step": policy.step, "checkpoint": str(policy.checkpoint),
                             "success_tol": env.core.success_tol, "success_worst_tol": env.core.success_worst_tol,
                             "max_steps": env.core.max_steps,
                             "mean_final_error": result["mean_final_error"], "deterministic": True,
                             **(acting.stats() if args.rollouts else {})})
        gif = None if args.no_gif else write_gif(out / "episodes.gif", recorder, result["targets"],
                                                 result["episodes"])
    solved = [e["steps"] for e in result["episodes"] if e["success"]]
    moves = f", {sum(solved) / len(solved):.2f} moves to success" if solved else ""
    how = f" acting by {args.rollouts} rollouts of {args.rollout_moves} moves" if args.rollouts else ""
    at = f" at {env.core.success_tol * 1000:g} mm" + (f" ({env.core.success_worst_tol * 1000:g} mm worst node)"
                                                     if env.core.success_worst_tol else "")
    print(f"{policy.algo} at step {policy.step}{how}: success rate{at} {result['success_rate']:.2f}{moves} over "
          f"{episodes} episodes on {label} (seed {seed}) -> {out}/results.json, eval_episodes.png"
          + (", episodes.gif" if gif else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
