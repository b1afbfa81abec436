"""Off-the-shelf Stable-Baselines3 SAC on DiffDLO/ShapeControl-v0, evaluated exactly like agents.sac.

    python benchmarks/studies/sb3_sac.py --total-steps 20000 --num-envs 16 --seed 0 --out runs/sb3-sac-s0

The comparison point for our SAC: same env (points observations, node actions, position-orientation
reward, random targets), same update-to-data ratio (``--gradient-steps`` per vector step, default = num_envs, i.e.
one update per transition as in SB3's single-env default), SB3's own vectorization (``make_vec_env``: a
DummyVecEnv of single envs, as an SB3 user would run it), and the same evaluation as ``agents.sac``
(``agents.common.evaluation.evaluate`` on ``--eval-episodes`` episodes from seeds 10000 + i, deterministic policy).
Writes ``results.json`` (the fields every method writes, method "sb3_sac") and prints the wall time. Needs the [dev] extra (SB3).
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))   # run as a script: the repository root

from agents.common.evaluation import evaluate
from benchmarks.studies import sb3_common
from diffdlo.envs import ENV_ID, BatchedShapeControl


def main() -> None:
    parser = sb3_common.parser(__doc__, total_steps=20_000, eval_episodes=50, out="runs/sb3-sac")
    parser.add_argument("--num-envs", type=int, default=16)
    parser.add_argument("--gradient-steps", type=int, default=None, help="updates per vector step (default: num_envs)")
    args = parser.parse_args()
    try:
        from stable_baselines3 import SAC
        from stable_baselines3.common.env_util import make_vec_env
    except ImportError as exc:
        raise SystemExit(f"stable-baselines3 is missing ({exc}): pip install -c constraints.txt -e '.[dev]'")

    torch.set_num_threads(args.threads)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    kwargs = dict(target=args.target, obs_type="points", action_type="node", reward="position_orientation")
    venv = make_vec_env(lambda: gym.make(ENV_ID, **kwargs), n_envs=args.num_envs, seed=args.seed)
    model = SAC("MultiInputPolicy", venv, learning_starts=100, batch_size=256, buffer_size=1_000_000,
                gradient_steps=args.gradient_steps or args.num_envs, train_freq=1, seed=args.seed, verbose=0)
    t0 = time.perf_counter()
    model.learn(total_timesteps=args.total_steps, progress_bar=False)
    train_s = time.perf_counter() - t0

    def policy(obs, deterministic: bool) -> torch.Tensor:
        batch = {k: v.cpu().numpy() for k, v in obs.items()}
        action, _ = model.predict(batch, deterministic=deterministic)
        return torch.as_tensor(np.asarray(action), dtype=torch.float64)

    eval_env = BatchedShapeControl(num_envs=min(args.eval_episodes, 16), **kwargs)
    result = evaluate(policy, eval_env, args.eval_episodes, deterministic=True, seed=args.eval_seed)
    wall = time.perf_counter() - t0
    path = sb3_common.write_record(out, "sb3_sac", args, result, env_steps=args.total_steps, wall_s=wall,
                                   train_s=train_s, mean_reward=result["mean_reward"],
                                   gradient_steps=args.gradient_steps or args.num_envs, num_envs=args.num_envs)
    print(f"sb3 SAC: {args.total_steps} steps in {train_s:.0f} s; eval success {result['success_rate']:.2f}, "
          f"mean final error {result['mean_final_error'] * 100:.1f} cm, mean reward {result['mean_reward']:.0f} "
          f"-> {path}")


if __name__ == "__main__":
    main()
