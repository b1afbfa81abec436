"""Env steps per second of DiffDLO/ShapeControl-v0 with the default params (params/cable.yaml).

Single env (gymnasium.make, B = 1) and native vector env (gymnasium.make_vec, B = 64), for points and image
observations; at least --steps steps and --min-time seconds each
after a seeded reset (a step is a full grasp-drag-release-settle move).
Prints a table and a final JSON line.  Usage: python benchmarks/env_speed.py [--steps 4] [--min-time 2] [--batch 64]
"""
from __future__ import annotations

import argparse
import json
import time

import gymnasium as gym
import numpy as np
import torch

import diffdlo  # noqa: F401  (registers the env)

ENV_ID = "DiffDLO/ShapeControl-v0"


def measure(num_envs: int, obs_type: str, steps: int, min_time: float, device: str, backend: str = "auto") -> dict:
    """At least ``steps`` steps, continued until ``min_time`` seconds have passed (at most 500 steps)."""
    if num_envs == 1:
        env = gym.make(ENV_ID, obs_type=obs_type, device=device, backend=backend)
    else:
        env = gym.make_vec(ENV_ID, num_envs=num_envs, obs_type=obs_type, device=device, backend=backend)
    env.reset(seed=0)
    env.action_space.seed(0)
    env.step(env.action_space.sample())                     # warm-up
    t = time.perf_counter()
    done = 0
    while done < steps or (time.perf_counter() - t < min_time and done < 500):
        env.step(env.action_space.sample())
        done += 1
    wall = time.perf_counter() - t
    steps = done
    env.close()
    return {"num_envs": num_envs, "obs_type": obs_type, "steps": steps, "wall_s": round(wall, 3),
            "env_steps_per_s": round(num_envs * steps / wall, 2)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=4, help="at least this many steps per measurement")
    ap.add_argument("--min-time", type=float, default=2.0, help="and at least this many seconds")
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--backend", default="auto", choices=["auto", "kernel", "torch"],
                    help="simulator backend; 'torch' is the eager reference path")
    args = ap.parse_args()
    rows = []
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, device {args.device}")
    print(f"{'env':>12} {'obs':>8} {'steps':>6} {'wall [s]':>9} {'env steps/s':>12}")
    for num_envs in (1, args.batch):
        for obs_type in ("points", "image"):
            r = measure(num_envs, obs_type, args.steps, args.min_time, args.device, args.backend)
            rows.append(r)
            name = "make" if num_envs == 1 else f"make_vec {num_envs}"
            print(f"{name:>12} {obs_type:>8} {r['steps']:>6} {r['wall_s']:>9.2f} {r['env_steps_per_s']:>12.2f}",
                  flush=True)
    print(json.dumps({"benchmark": "env_speed", "device": args.device, "backend": args.backend, "results": rows}))


if __name__ == "__main__":
    np.set_printoptions(precision=3)
    main()
