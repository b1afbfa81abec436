"""Acting by policy rollouts through the simulator: one step of policy improvement over a trained policy.

Bertsekas's rollout algorithm (also "MPC with a base policy", Tesauro & Galperin's on-line policy improvement): at
every move, try ``candidates`` first moves on copies of the rope in the simulator (the policy's own deterministic
move and ``candidates - 1`` moves sampled from the policy), let the policy finish each copy deterministically for at
most ``moves`` more moves, and make the first move of the copy that reached the target in the fewest moves (among
equals the policy's own move; copies that did not reach it ranked by their final shape error). On a deterministic simulator the chosen move's
copy is exactly what the policy would then do, so the result takes no more moves than the policy alone on any
episode where that copy succeeded within ``moves`` moves — the learned policy becomes a planner's search prior and
its own value estimate, without any value network (a learned V, scored one move ahead, was tried first: its errors
are what the argmax finds, and it took more moves than the policy alone; docs/AGENTS.md).

    acting = PolicyRollouts(policy, options, candidates=32, moves=20)      # policy(obs, deterministic) -> actions
    actions = acting(obs)                                                  # (B, A): one improved move per rope

The copies of every rope of the batch are simulated together (B x candidates ropes, one batched move per rollout
step). Its cost: ``sim_evals`` rope-moves and ``wall_s`` seconds so far, over ``decisions`` moves decided.
A learner acts this way in its final evaluation with ``--set rollout_candidates=C`` (agents/common/config.py RunOptions;
``rollout_moves`` the horizon), and any run's checkpoint with ``python -m agents.tools.evaluate RUN --rollouts C``.
"""
from __future__ import annotations

import time
from typing import Any, Callable

import torch

from agents.common.envs import TrainEnv
from diffdlo.envs import BatchedShapeControl, EnvOptions

ROLLOUT_OBS = ("points",)        # observations that show the rope and the target, so the simulator can copy them


def check_acts_by_rollouts(algo: str, obs_type: str) -> None:
    """ValueError unless a run of ``algo`` on observations ``obs_type`` can act by policy rollouts."""
    if algo == "planet":
        raise ValueError("PlaNet already plans; acting by policy rollouts is for the learners that act from the "
                         "observation (sac, ppo, apg, distill)")
    check_rollout_obs(obs_type)


def check_rollout_obs(obs_type: str) -> None:
    if obs_type not in ROLLOUT_OBS:
        raise ValueError(f"acting by rollouts copies the rope and target from the observation: it needs obs "
                         f"{list(ROLLOUT_OBS)}, got {obs_type!r}")


class PolicyRollouts:
    """``acting(obs, deterministic=True) -> (B, A)``: the rollout-improved moves of a batched ``policy(obs,
    deterministic)`` (a learner's acting network, as ``agents.tools.policy`` builds it) on observations of the task
    ``options`` (an EnvOptions, or a dict of its keyword arguments; obs "points"). ``seed``: the candidates are
    sampled from a generator seeded with it (the same observations give the same moves)."""

    def __init__(self, policy: Callable[[Any, bool], torch.Tensor], options: EnvOptions | dict[str, Any],
                 candidates: int = 32, moves: int = 20, seed: int = 0, env_device: str | torch.device = "cpu",
                 learner_device: str | torch.device | None = None):
        if int(candidates) < 1:
            raise ValueError(f"rollout candidates must be >= 1, got {candidates}")
        if int(moves) < 0:
            raise ValueError(f"rollout moves must be >= 0, got {moves}")
        self.options = options if isinstance(options, EnvOptions) else EnvOptions(**options)
        check_rollout_obs(self.options.obs_type)
        self.policy = policy
        self.candidates, self.moves, self.seed = int(candidates), int(moves), int(seed)
        self.env_device, self.learner_device = env_device, learner_device
        self._copies: TrainEnv | None = None
        self.decisions, self.sim_evals, self.wall_s = 0, 0, 0.0

    def _env(self, n: int) -> TrainEnv:
        """The simulator's copies: one env of n ropes, kept while the batch size stays."""
        if self._copies is None or self._copies.num_envs != n:
            core = BatchedShapeControl(n, self.options, device=self.env_device)
            core.reset(seed=0)                       # set_state needs a first state; every rope is overwritten
            self._copies = TrainEnv(core, device=self.learner_device)
        return self._copies

    def _candidates(self, obs: dict[str, torch.Tensor]) -> torch.Tensor:
        """(B, C, A): the policy's deterministic move first, then C - 1 sampled ones."""
        first = self.policy(obs, True)
        if self.candidates == 1:
            return first[:, None]
        repeated = {k: v.repeat_interleave(self.candidates - 1, 0) for k, v in obs.items()}
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(self.seed + self.decisions)      # the CPU generator the policy samples with
            sampled = self.policy(repeated, False)
        b = first.shape[0]
        return torch.cat([first[:, None], sampled.reshape(b, self.candidates - 1, -1)], 1)

    @torch.no_grad()
    def __call__(self, obs: dict[str, torch.Tensor], deterministic: bool = True) -> torch.Tensor:
        t0 = time.perf_counter()
        pos, target = obs["node_poses"], obs["target_poses"]
        b, c = pos.shape[0], self.candidates
        cand = self._candidates(obs)
        env = self._env(b * c)
        core = env.core
        pegs = obs["pegs"].repeat_interleave(c, 0) if "pegs" in obs else None    # a route's board, copied too
        core.set_state(pos=pos.repeat_interleave(c, 0), target=target.repeat_interleave(c, 0), steps=0, pegs=pegs)
        _, _, term, trunc, info = core.step(cand.reshape(b * c, -1).to(core.device, core.dtype))
        moves, error, evals = moves_to_success(env, self.policy, info["is_success"].cpu(), (term | trunc).cpu(),
                                               self.moves)
        self.sim_evals += evals + b * c
        best = rank(moves.reshape(b, c), error.reshape(b, c))
        self.decisions += b
        self.wall_s += time.perf_counter() - t0
        return cand[torch.arange(b), best]

    def stats(self) -> dict[str, Any]:
        """The acting's figures for results.json."""
        n = max(self.decisions, 1)
        return {"acting": "policy rollouts through the simulator", "rollout_candidates": self.candidates,
                "rollout_moves": self.moves, "sim_evals_per_move": self.sim_evals / n,
                "rollout_s_per_move_batched": self.wall_s / n}


def moves_to_success(env: TrainEnv, policy: Callable[[Any, bool], torch.Tensor], success: torch.Tensor,
                     ended: torch.Tensor, moves: int) -> tuple[torch.Tensor, torch.Tensor, int]:
    """Let ``policy`` finish every rope of ``env`` (each has made one move: ``success``/``ended`` (n,) after it)
    deterministically for at most ``moves`` more moves. Returns the moves to success (n,) counting the first (inf
    where it never succeeded), the final shape errors (n,) [m] and the rope-moves made."""
    core = env.core
    done_at = torch.where(success, 1.0, float("inf")).double()
    alive = ~ended
    evals = 0
    for k in range(moves):
        if not bool(alive.any()):
            break
        actions = policy(env.observe(), True)
        _, _, term, trunc, info = core.step(actions.to(core.device, core.dtype), mask=alive)
        evals += int(alive.sum())
        done_at[alive & info["is_success"].cpu()] = 2.0 + k
        alive &= ~(term | trunc).cpu()
    return done_at, core.info()["shape_error"].cpu().double(), evals


def rank(moves: torch.Tensor, error: torch.Tensor) -> torch.Tensor:
    """(B, C) moves to success (inf: none) and final errors -> the index (B,) of each row's best candidate: the fewest
    moves; among equals the policy's own move (candidate 0) where it is one of them, else the lowest final error. A
    sampled move replaces the policy's only where it saves a move (or where no copy reached the target)."""
    big = moves.nan_to_num(posinf=float(torch.finfo(torch.float64).max))
    fewest = big == big.min(1, keepdim=True).values
    err = torch.where(fewest, error, torch.full_like(error, float("inf")))
    solved = torch.isfinite(moves).any(1)
    return torch.where(fewest[:, 0] & solved, torch.zeros_like(solved, dtype=torch.int64), err.argmin(1))
