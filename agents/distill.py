"""Expert iteration: a policy distilled from acting by rollouts (DAgger), then the rollouts run over the student
(Anthony et al. 2017's expert iteration; AlphaZero's loop with the simulator as the search's model), CleanRL-style
in one file: config -> networks -> loop.

    python -m agents.distill --teacher runs/ppo --target random --total-steps 32768 --out runs/distill

The teacher is a trained PPO run's hybrid policy acting by policy rollouts through the simulator (agents/common/rollout.py:
``teacher_candidates`` first moves, each finished by the policy for ``teacher_moves`` moves, the fewest moves to the
target kept). The student starts as a copy of that policy (same network, same feature normalization) and learns
the teacher's moves by maximum likelihood on the states it visits itself (DAgger, Ross et al. 2011): every batched
step, each rope's state is labelled with the teacher's move, and the move made is the teacher's with probability
``beta`` (halved at every fit) and the student's own otherwise. Every ``fit_every`` env steps the student is fit on
all the states so far (``epochs`` passes); every ``teacher_every`` env steps (0: never) the teacher's base policy
becomes a copy of the student: the search is then guided by the policy that was distilled from it.

The result is a policy network that acts in about a millisecond a move, evaluated on its own (results.json); with
``--set rollout_candidates=C`` its final evaluation acts by rollouts over it instead (the policy alone is kept under
"policy_alone"). Its checkpoint loads like a PPO one (``agents.tools.policy.load_policy``, ``python -m agents.tools.evaluate``).
The env steps are the student's (labelled states); the teacher's simulated rope-moves are reported as
``teacher_sim_evals``.
"""
from __future__ import annotations

import copy
import dataclasses
import sys
from pathlib import Path
from typing import Any

import torch
import torch.nn as nn

from agents.models import hybrid
from agents.common.cli import run_cli
from agents.common.config import POLICIES, InputOptions, RunOptions, TaskOptions, check_model_free, part
from agents.common.checkpoints import load_weights
from agents.tools.policy import checkpoint_config, checkpoint_path, read_checkpoint
from agents.ppo import ActorCritic
from agents.common.rollout import PolicyRollouts, check_rollout_obs
from agents.common.run import Run, learner
from diffdlo.utils.checks import option

# the network keys the student takes from its teacher's config (it starts as the teacher's policy)
NETWORK_KEYS = ("policy", "hidden", "log_std_init", "inputs")
# the task keys that must agree with the teacher's: what its network reads and how its moves are decoded
TEACHER_TASK_KEYS = ("obs", "action", "params", "param_overrides", "image_size")


# ====================================================================== config (defaults: params/distill.yaml)
@dataclasses.dataclass
class DistillConfig:
    task: TaskOptions = part(TaskOptions)
    run: RunOptions = part(RunOptions, total_steps=32_768, num_envs=64, eval_every=8192, checkpoint_every=8192,
                           log_every=1)
    inputs: InputOptions = part(InputOptions)
    teacher: str = option("", help="a PPO run folder (or its checkpoint.pt) with a hybrid policy")
    teacher_candidates: int = option(32, "[1, inf)", help="the teacher's rollouts: candidate first moves ...")
    teacher_moves: int = option(20, "[0, inf)",
                                help="... each finished by the base policy for at most this many moves")
    teacher_every: int = option(0, "[0, inf)",
                                help='env steps between "the base policy becomes the student" (0: never)')
    fit_every: int = option(8192, "[1, inf)", help="env steps between fits on all the labelled states so far")
    beta: float = option(0.5, "[0, 1]", help="probability of making the teacher's move (halved after every fit)")
    lr: float = option(1e-4, "(0, inf)", help="the student's Adam")
    epochs: int = option(4, "[1, inf)", help="passes over the labelled states per fit")
    batch_size: int = option(1024, "[1, inf)", help="labelled states per minibatch")
    # the network: overwritten by the teacher's at the start (the student is a copy of it)
    policy: str = option("hybrid", choices=POLICIES, help="the student's policy head (hybrid only)")
    hidden: list = option(factory=lambda: [256, 256], layers=True, help="the student's hidden layers")
    log_std_init: float = option(-0.6931471805599453, help="the student's initial drag log std")

    def check(self) -> None:
        check_model_free(self)
        if not self.teacher:
            raise ValueError("teacher: give the PPO run to distill, --set teacher=RUN_DIR")
        if self.policy != "hybrid":
            raise ValueError(f"policy: the student is a hybrid policy (node + drag), got {self.policy!r}")
        check_rollout_obs(self.task.obs)


def teacher_checkpoint(cfg: DistillConfig) -> tuple[dict[str, Any], Any, Path]:
    """The teacher's checkpoint and its PPO config; ValueError when it is not a hybrid PPO of the same task."""
    path = checkpoint_path(cfg.teacher)
    ck = read_checkpoint(path)
    if ck["algo"] not in ("ppo", "distill"):
        raise ValueError(f"teacher {cfg.teacher!r}: a {ck['algo']} run; the teacher must be a ppo (or distill) run")
    tcfg = checkpoint_config(ck, path, cfg.run.device)
    if tcfg.policy != "hybrid":
        raise ValueError(f"teacher {cfg.teacher!r}: its policy is {tcfg.policy!r}; distillation needs 'hybrid'")
    differ = [f"{k} (the teacher's {getattr(tcfg.task, k)!r}, this run's {getattr(cfg.task, k)!r})"
              for k in TEACHER_TASK_KEYS if getattr(tcfg.task, k) != getattr(cfg.task, k)]
    if differ:
        raise ValueError(f"teacher {cfg.teacher!r} reads another task: {'; '.join(differ)}")
    return ck, tcfg, path


def with_teacher_network(cfg: DistillConfig, tcfg) -> DistillConfig:
    return dataclasses.replace(cfg, **{k: copy.deepcopy(getattr(tcfg, k)) for k in NETWORK_KEYS})


# ====================================================================== the labelled states
class Labels:
    """Every state the student visited (observations) and the teacher's move there (stored hybrid rows)."""

    def __init__(self) -> None:
        self.obs: dict[str, list[torch.Tensor]] = {}
        self.actions: list[torch.Tensor] = []

    def add(self, obs: dict[str, torch.Tensor], actions: torch.Tensor) -> None:
        for k, v in obs.items():
            self.obs.setdefault(k, []).append(v.detach().cpu())
        self.actions.append(actions.detach().cpu())

    def __len__(self) -> int:
        return sum(len(a) for a in self.actions)

    def tensors(self, device) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
        return ({k: torch.cat(v).to(device) for k, v in self.obs.items()}, torch.cat(self.actions).to(device))

    def state_dict(self) -> dict[str, Any]:
        if not self.actions:
            return {"obs": {}, "actions": None}
        obs, actions = self.tensors("cpu")
        return {"obs": obs, "actions": actions}

    def load_state_dict(self, s: dict[str, Any]) -> None:
        self.obs = {k: [v] for k, v in s["obs"].items()}
        self.actions = [] if s["actions"] is None else [s["actions"]]


def stored_action(env_action: torch.Tensor, n_nodes: int) -> torch.Tensor:
    """The teacher's env move (B, 3) -> the hybrid head's stored row (node, drag in [-1, 1])."""
    node, drag = hybrid.from_env_action(env_action, n_nodes)
    return hybrid.join(node, drag)


def imitation_loss(agent: ActorCritic, obs: dict[str, torch.Tensor], stored: torch.Tensor) -> tuple[torch.Tensor,
                                                                                                     torch.Tensor]:
    """-log pi(teacher's node, teacher's drag | state), averaged; and the fraction of states whose mode picks the
    teacher's node."""
    d, _ = agent.dist(obs)
    node, _ = hybrid.split(stored)
    return -d.log_prob(stored).mean(), (d.cat.logits.argmax(-1) == node).float().mean()


def fit(agent: ActorCritic, opt: torch.optim.Optimizer, labels: Labels, epochs: int, batch_size: int,
        device) -> dict[str, float]:
    """``epochs`` passes over every labelled state in shuffled minibatches; returns the last pass's mean loss and the
    node agreement over all states after it."""
    obs, stored = labels.tensors(device)
    n = len(stored)
    losses = []
    for _ in range(epochs):
        losses = []
        for idx in torch.randperm(n).split(batch_size):
            loss, _ = imitation_loss(agent, {k: v[idx] for k, v in obs.items()}, stored[idx])
            opt.zero_grad()
            loss.backward()
            nn.utils.clip_grad_norm_(agent.parameters(), 0.5)
            opt.step()
            losses.append(loss.item())
    with torch.no_grad():
        _, agree = imitation_loss(agent, obs, stored)
    return {"imitation_loss": sum(losses) / len(losses), "node_agreement": float(agree), "states": n}


# ====================================================================== training loop
@learner
def train(cfg: DistillConfig, out: Path | str, resume: bool = False, progress: bool = True) -> dict[str, Any]:
    ck_teacher, tcfg, tpath = teacher_checkpoint(cfg)
    cfg = with_teacher_network(cfg, tcfg)
    run = Run("distill", cfg, out, resume, progress)
    env, device, obs, p = run.env, run.device, run.obs, run.params
    student = ActorCritic(obs, env.core.action_dim, cfg, p.length, p.n_nodes).to(device)
    load_weights(student, ck_teacher["agent"], tpath, "agent")      # the student starts as the teacher's policy
    student.log_std.requires_grad_(False)                           # only the mode is imitated
    base = copy.deepcopy(student).eval()                            # the teacher's base policy
    opt = torch.optim.Adam([q for q in student.parameters() if q.requires_grad], lr=cfg.lr, eps=1e-5)
    labels = Labels()
    ck = run.start(agent=student, base=base, opt=opt, labels=labels)
    counters = ck["counters"] if ck else {"fits": 0, "teachers": 0, "teacher_decisions": 0, "teacher_sim_evals": 0,
                                          "last_fit": 0, "last_teacher": 0}
    obs, logger, bar = run.obs, run.logger, run.bar

    def student_policy(o: Any, deterministic: bool = True) -> torch.Tensor:
        return student.act(o, deterministic)

    def base_policy(o: Any, deterministic: bool = True) -> torch.Tensor:
        return base.act(o, deterministic)

    # the teacher: rollouts over the base policy; its sampling continues where a resumed run stopped
    teacher = PolicyRollouts(base_policy, cfg.task.env_options(p), cfg.teacher_candidates, cfg.teacher_moves,
                             seed=cfg.run.seed, env_device=cfg.run.env_device or cfg.run.device, learner_device=device)
    teacher.decisions, teacher.sim_evals = counters["teacher_decisions"], counters["teacher_sim_evals"]

    if cfg.run.total_steps % cfg.run.num_envs:
        print(f"distill: {cfg.run.total_steps} steps are not a whole number of batched steps of {cfg.run.num_envs} "
              f"ropes: the run makes {-(-cfg.run.total_steps // cfg.run.num_envs) * cfg.run.num_envs}", file=sys.stderr)
    while run.step < cfg.run.total_steps:
        with torch.no_grad():
            target_moves = teacher(obs)
            own = student_policy(obs)
        counters["teacher_decisions"], counters["teacher_sim_evals"] = teacher.decisions, teacher.sim_evals
        labels.add(obs, stored_action(target_moves, p.n_nodes))
        beta = cfg.beta * 0.5 ** counters["fits"]
        take_teacher = (torch.rand(len(own)) < beta).to(own.device)[:, None]
        next_obs, reward, term, trunc, info, _ = env.step(torch.where(take_teacher, target_moves, own))
        run.count(info, term, trunc)
        obs = next_obs
        if run.step - counters["last_fit"] >= cfg.fit_every or run.step >= cfg.run.total_steps:
            counters["last_fit"] = run.step
            row = fit(student, opt, labels, cfg.epochs, cfg.batch_size, device)
            counters["fits"] += 1
            logger.log("train", run.step, {**row, "beta": beta, "teacher_sim_evals": counters["teacher_sim_evals"]})
            run.log_rollout()
        if cfg.teacher_every and run.step - counters["last_teacher"] >= cfg.teacher_every:
            counters["last_teacher"] = run.step
            base.load_state_dict(student.state_dict())               # expert iteration: search over the student
            counters["teachers"] += 1
        run.evaluate_if_due(lambda: run.evaluate(student_policy))
        run.checkpoint_if_due(lambda: {"agent": student, "base": base, "opt": opt, "labels": labels,
                                       "counters": dict(counters)})
    return run.finish(student_policy, extra={"teacher": str(tpath), "teacher_step": int(ck_teacher["step"]),
                                             "teacher_sim_evals": counters["teacher_sim_evals"],
                                             "teacher_updates": counters["teachers"]})


def main(argv: list[str] | None = None) -> int:
    return run_cli(DistillConfig, "distill", __doc__, train, argv)


if __name__ == "__main__":
    sys.exit(main())
