"""Does a learned value guide a one-move search? PPO's critic scored one move ahead through the simulator.

At every move: the policy's deterministic move and ``candidates - 1`` moves sampled from it are simulated from the
rope's state, each scored by the env's reward plus gamma V(next state) (PPO's critic; no bootstrap where the move
ended the episode), and the best is made. That is TD-MPC's planning objective at horizon 1 on the true simulator,
with the policy as the sampling prior. Printed beside the policy alone and acting by policy rollouts
(agents/common/rollout.py, whose value estimate is the policy's own simulated moves to the target) on the same episodes.

    python -m benchmarks.studies.value_lookahead runs/compare/ppo/tuned/random/seed0 --candidates 16 64 256

Episode i is ``env.reset(seed=EVAL_SEED + i)`` (default: the run's eval_seed, as its evaluation and the comparison's
cell). Prints moves to success and ms per move (one rope at a time, on this CPU).
"""
from __future__ import annotations

import argparse
import sys
import time
from typing import Any, Callable

import torch

from agents.common.envs import TrainEnv
from agents.common.evaluation import evaluate
from agents.common.checkpoints import load_weights
from agents.tools.policy import checkpoint_config, checkpoint_path, read_checkpoint
from agents.ppo import ActorCritic
from agents.common.rollout import PolicyRollouts
from diffdlo.envs import BatchedShapeControl, EnvOptions


class ValueLookahead:
    """``acting(obs) -> (1, A)``: the candidate maximising reward + gamma (1 - terminated) V(next observation)."""

    def __init__(self, agent: ActorCritic, options: EnvOptions, candidates: int, gamma: float, seed: int = 0):
        self.agent, self.candidates, self.gamma, self.seed, self.calls = agent, candidates, gamma, seed, 0
        core = BatchedShapeControl(candidates, options)
        core.reset(seed=0)
        self.copies = TrainEnv(core)

    @torch.no_grad()
    def __call__(self, obs: dict[str, torch.Tensor], deterministic: bool = True) -> torch.Tensor:
        d, _ = self.agent.dist(obs)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(self.seed + self.calls)
            sampled = torch.cat([d.sample() for _ in range(self.candidates - 1)]) if self.candidates > 1 else None
        self.calls += 1
        stored = d.mode() if sampled is None else torch.cat([d.mode(), sampled])
        moves = self.agent.env_action(stored)
        c = len(moves)
        core = self.copies.core
        core.set_state(pos=obs["node_poses"].expand(c, -1, -1), target=obs["target_poses"][0], steps=0)
        _, reward, term, _, _ = core.step(moves.to(core.dtype))
        value = self.agent.value(self.copies.observe()).to(reward.dtype)
        return moves[int(one_move_score(reward, term, value, self.gamma).argmax())][None]


def one_move_score(reward: torch.Tensor, terminated: torch.Tensor, value: torch.Tensor, gamma: float) -> torch.Tensor:
    """TD-MPC's score at horizon 1: reward + gamma V(next state), with no bootstrap where the move ended the episode
    (success, or a failure by leaving the table): there is no next state to value."""
    return reward + gamma * (~terminated).to(reward.dtype) * value


class Timed:
    """An acting function that also counts its calls and their seconds (one call: one move of one rope)."""

    def __init__(self, acting: Callable) -> None:
        self.acting, self.calls, self.wall = acting, 0, 0.0

    def __call__(self, obs: Any, deterministic: bool = True) -> torch.Tensor:
        t0 = time.perf_counter()
        action = self.acting(obs, deterministic)
        self.wall += time.perf_counter() - t0
        self.calls += 1
        return action


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.studies.value_lookahead", description=__doc__.split("\n\n")[0])
    ap.add_argument("run_dir", help="a PPO run (hybrid policy, obs points)")
    ap.add_argument("--candidates", type=int, nargs="+", default=[16, 64, 256])
    ap.add_argument("--rollouts", type=int, default=32, help="candidates of the policy rollouts row (0: none)")
    ap.add_argument("--episodes", type=int, default=20)
    ap.add_argument("--eval-seed", type=int, default=None, help="default: the run's eval_seed")
    args = ap.parse_args(argv)
    if any(c < 1 for c in args.candidates) or args.episodes < 1 or args.rollouts < 0:
        ap.error(f"--candidates and --episodes must be >= 1 and --rollouts >= 0, got --candidates {args.candidates}, "
                 f"--episodes {args.episodes}, --rollouts {args.rollouts}")
    path = checkpoint_path(args.run_dir)
    try:
        ck = read_checkpoint(path)
        if ck["algo"] != "ppo":
            raise ValueError(f"{path}: a {ck['algo']} run; the critic read here is PPO's")
        cfg = checkpoint_config(ck, path, "cpu")
    except (FileNotFoundError, ValueError) as exc:
        ap.error(str(exc))
    torch.set_num_threads(1)
    options = cfg.task.env_options()
    example = TrainEnv(BatchedShapeControl(1, options)).reset(seed=0)
    p = cfg.task.cable_params()
    agent = ActorCritic(example, 3, cfg, p.length, p.n_nodes)
    load_weights(agent, ck["agent"], path, "agent")
    agent.eval()
    seed = cfg.run.eval_seed if args.eval_seed is None else args.eval_seed

    def alone(o, deterministic=True):
        with torch.no_grad():
            return agent.act(o, deterministic)
    rows = [("policy alone", alone)]
    rows += [(f"value lookahead, {c} candidates", ValueLookahead(agent, options, c, cfg.gamma))
             for c in args.candidates]
    if args.rollouts:
        rows.append((f"policy rollouts, {args.rollouts} x 20", PolicyRollouts(alone, options, args.rollouts, 20, seed)))
    print(f"{path} (gamma {cfg.gamma}), episodes {seed}..{seed + args.episodes - 1}:")
    for name, acting in rows:                           # one rope at a time: a call is one move's latency
        timed = Timed(acting)
        episodes = evaluate(timed, TrainEnv(BatchedShapeControl(1, options)), args.episodes, seed=seed)["episodes"]
        solved = [e["steps"] for e in episodes if e["success"]]
        mean = f"{sum(solved) / len(solved):.2f}" if solved else "-"
        print(f"  {name:34s} success {len(solved)}/{args.episodes}  moves {mean:>6s}  "
              f"{1000 * timed.wall / max(timed.calls, 1):7.1f} ms/move")
    return 0


if __name__ == "__main__":
    sys.exit(main())
