"""Env steps per second of DiffDLO/ShapeControl-v0 with the default params (params/cable.yaml).

Single env (gymnasium.make, B = 1) and native vector env (gymnasium.make_vec, B = 64), for points and image
observations; at least --steps steps and --min-time seconds each
after a seeded reset (a step is a full grasp-drag-release-settle move).
Prints a table and a final JSON line.  Usage: python benchmarks/speed/env_speed.py [--steps 4] [--min-time 2] [--batch 64]

    python benchmarks/speed/env_speed.py --device cuda [--batches 1 64 1024 16384 65536]

On CUDA it times the torch-native batched env (diffdlo.envs.core.BatchedShapeControl, points observations,
tensors on the device, one batched move per step) for each B with the Triton backend, the eager torch backend on
the same GPU (up to --eager-max) and the CPU C++ kernel (device cpu, up to --cpu-max) in the same run; the
forward+backward time of a move is in benchmarks/speed/sim_speed.py --device cuda.
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


def measure_batched(num_envs: int, steps: int, min_time: float, device: str, backend: str) -> dict:
    """Env steps/s of the torch-native batched env (points observations): at least ``steps`` steps and
    ``min_time`` seconds after a seeded reset and one warm-up step."""
    from diffdlo.envs.core import BatchedShapeControl
    env = BatchedShapeControl(num_envs=num_envs, device=device, backend=backend)
    env.reset(seed=0)
    g = torch.Generator().manual_seed(0)

    def step():
        env.step(torch.rand(num_envs, env.action_dim, generator=g).to(env.device), autoreset="same_step")

    def sync():
        if env.device.type == "cuda":
            torch.cuda.synchronize(env.device)

    step()
    sync()
    t = time.perf_counter()
    done = 0
    while done < steps or (time.perf_counter() - t < min_time and done < 500):
        step()
        done += 1
    sync()
    wall = time.perf_counter() - t
    return {"num_envs": num_envs, "device": device, "backend": backend, "uses_triton": env.sim.engine == "triton",
            "uses_kernel": env.sim.engine == "kernel", "steps": done, "wall_s": round(wall, 3),
            "env_steps_per_s": round(num_envs * done / wall, 2)}


def cuda_main(args) -> None:
    rows = []
    print(f"torch {torch.__version__}, {torch.cuda.get_device_name(args.device)}, "
          f"CPU {torch.get_num_threads()} threads")
    print(f"{'B':>6} {'path':>22} {'steps':>6} {'wall [s]':>9} {'env steps/s':>12}")
    for batch in args.batches:
        runs = [(args.device, "triton"), ("cpu", "auto")]
        if batch <= args.eager_max:
            runs.insert(1, (args.device, "torch"))
        for device, backend in runs:
            if device == "cpu" and batch > args.cpu_max:
                continue
            r = measure_batched(batch, args.steps, args.min_time, device, backend)
            rows.append(r)
            name = f"{device} {backend}" + (" (C++ kernel)" if r["uses_kernel"] else "")
            print(f"{batch:>6} {name:>22} {r['steps']:>6} {r['wall_s']:>9.2f} {r['env_steps_per_s']:>12.2f}",
                  flush=True)
    print(json.dumps({"benchmark": "env_speed", "device": args.device, "mode": "batched_points", "results": rows}))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=4, help="at least this many steps per measurement")
    ap.add_argument("--min-time", type=float, default=2.0, help="and at least this many seconds")
    ap.add_argument("--batch", type=int, default=64)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--backend", default="auto", choices=["auto", "kernel", "torch", "triton"],
                    help="simulator backend; 'torch' is the eager reference path")
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 64, 1024, 16384, 65536],
                    help="cuda: batch sizes of the batched env")
    ap.add_argument("--eager-max", type=int, default=1024, help="cuda: largest B timed on the eager GPU path")
    ap.add_argument("--cpu-max", type=int, default=65536, help="cuda: largest B timed on the CPU kernel")
    args = ap.parse_args()
    if args.device.startswith("cuda"):
        cuda_main(args)
        return
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
