"""Speed of the 3-D two-gripper task (DiffDLO/Cable3D-v0, docs/CABLE3D.md), the fused C++ kernel against the eager
chain in one run: env steps per second at several batch sizes (one step: the grippers' 1 s motion and the settle,
capped at ``--settle-time``, the env's 5 s by default; the same seeds and actions on both engines), one CEM
planning step (the planner's defaults), forward + backward through one move (the kernel's adjoint against the eager
chain's autograd), and how long each cable takes to come to rest after a random move (the settle's share of a step).

    python benchmarks/speed/cable3d_speed.py                       # DLO3, B = 1 64 1024, float32, 2 threads
    python benchmarks/speed/cable3d_speed.py --batches 1 64 --cable DLO5 --dtype float64
"""
from __future__ import annotations

import argparse
import sys
import time

import torch

from diffdlo.chain3d import grippers as gr
from diffdlo.chain3d import kernel
from diffdlo.chain3d.cables import cable_names
from diffdlo.envs.cable3d import BatchedCable3D
from diffdlo.tasks import cable3d as rules


def steps_per_second(cable: str, batch: int, dtype: torch.dtype, settle_time: float, engine: str,
                     min_seconds: float = 1.0) -> float:
    """Env steps per second of B envs stepping random actions: as many batched steps as fill ``min_seconds``
    (at least one), each from where the last left the cables."""
    core = BatchedCable3D(batch, cable=cable, settle_time=settle_time, dtype=dtype, engine=engine)
    core.seed(list(range(batch)))
    core.reset()
    generator = torch.Generator().manual_seed(0)
    steps, t0 = 0, time.perf_counter()
    while steps == 0 or time.perf_counter() - t0 < min_seconds:
        core.step(torch.rand(batch, rules.ACTION_DIM, generator=generator, dtype=dtype) * 2 - 1)
        steps += 1
    return steps * batch / (time.perf_counter() - t0)


def kernel_share(cable: str, dtype: torch.dtype, steps: int = 200) -> tuple[float, float]:
    """(ms per env step at B = 1, the share of it inside the kernel's call): the rest is the env's torch work around
    it (the action's decode, the gripper path, observations, metrics)."""
    core = BatchedCable3D(1, cable=cable, dtype=dtype)
    core.seed([0])
    core.reset()
    generator = torch.Generator().manual_seed(0)
    inner, spent = kernel._Move.forward, [0.0]

    def timed(ctx, *args):
        t0 = time.perf_counter()
        out = inner(ctx, *args)
        spent[0] += time.perf_counter() - t0
        return out
    kernel._Move.forward = staticmethod(timed)
    try:
        t0 = time.perf_counter()
        for _ in range(steps):
            core.step(torch.rand(1, rules.ACTION_DIM, generator=generator, dtype=dtype) * 2 - 1)
        total = time.perf_counter() - t0
    finally:
        kernel._Move.forward = staticmethod(inner)
    return 1000 * total / steps, spent[0] / total


def planning_step(cable: str, dtype: torch.dtype, engine: str) -> float:
    from planners.cable3d import CEMPlanner
    core = BatchedCable3D(1, cable=cable, dtype=dtype, engine=engine)
    core.seed([0])
    core.reset()
    planner = CEMPlanner(core)
    t0 = time.perf_counter()
    planner.plan(core.x[0], core.target[0])
    return time.perf_counter() - t0


def backward_move(cable: str, dtype: torch.dtype, batch: int, engine: str) -> tuple[float, float]:
    """Seconds of one move of B cables (1 s of motion, the settle capped at 1 s as the planners' is) forward, and
    of the backward of a loss on where it leaves them, w.r.t. the grippers' goal."""
    core = BatchedCable3D(batch, cable=cable, dtype=dtype)
    core.seed(list(range(batch)))
    core.reset()
    shift = torch.zeros(batch, 2, 3, dtype=dtype, requires_grad=True)
    poses = gr.poses_of(core.x)
    t0 = time.perf_counter()
    out = gr.move(core.x, None, gr.Grippers(poses.pos + shift, poses.dirs), core.cable, move_frames=core.move_frames,
                  rest_speed=core.rest_speed, check_frames=10, settle_frames=100, engine=engine)
    forward = time.perf_counter() - t0
    rules.marker_errors(out.x, core.target).mean().backward()
    return forward, time.perf_counter() - t0 - forward


def rest_times(cable: str, batch: int, dtype: torch.dtype) -> list[float]:
    core = BatchedCable3D(batch, cable=cable, settle_time=10.0, dtype=dtype)
    core.seed(list(range(batch)))
    core.reset()
    actions = torch.rand(batch, rules.ACTION_DIM, generator=torch.Generator().manual_seed(1), dtype=dtype) * 2 - 1
    info = core.step(actions)[-1]
    return ((info["frames"] - core.move_frames).float() * 0.01).tolist()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python benchmarks/speed/cable3d_speed.py", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cable", default="DLO3", choices=cable_names())
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 64, 1024])
    ap.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--settle-time", type=float, default=5.0, help="[s] the settle's cap in the timed steps (the "
                    "env's default)")
    ap.add_argument("--rest", type=int, default=8, help="moves per cable for the rest times (0: skip)")
    args = ap.parse_args(argv)
    if min(args.batches) < 1 or args.threads < 1 or args.rest < 0:
        ap.error("--batches and --threads must be >= 1, --rest >= 0")
    torch.set_num_threads(args.threads)
    dtype = getattr(torch, args.dtype)
    if not kernel.available():
        print(f"the kernel is unavailable ({kernel.unavailable_reason()}): nothing to compare", file=sys.stderr)
        return 1
    print(f"cable {args.cable}, {args.dtype}, {args.threads} threads, settle capped at {args.settle_time:g} s")
    print("| B | kernel: env steps / s | eager: env steps / s | kernel / eager |\n|---|---|---|---|")
    for b in args.batches:
        fast, slow = (steps_per_second(args.cable, b, dtype, args.settle_time, e) for e in ("auto", "eager"))
        print(f"| {b} | {fast:,.0f} | {slow:,.1f} | {fast / slow:.0f}x |")
    ms, share = kernel_share(args.cable, dtype)
    print(f"B = 1: {ms:.2f} ms an env step, {100 * share:.0f} % of it in the kernel's call")
    fast, slow = (planning_step(args.cable, dtype, e) for e in ("auto", "eager"))
    print(f"one CEM planning step (128 candidates x 5 iterations, horizon 1): kernel {fast:.3f} s, eager {slow:.2f} s "
          f"({slow / fast:.0f}x)")
    print("\n| one move (1 s motion + up to 1 s settle), forward + backward | kernel [s] | eager [s] | kernel / eager |"
          "\n|---|---|---|---|")
    for b in (1, 8):
        fast, slow = (sum(backward_move(args.cable, dtype, b, e)) for e in ("auto", "eager"))
        print(f"| B = {b} | {fast:.3f} | {slow:.2f} | {slow / fast:.0f}x |")
    if args.rest:
        print("\n| cable | seconds to rest after a random move (< 1 cm/s): median / max |\n|---|---|")
        for name in cable_names():
            t = sorted(rest_times(name, args.rest, dtype))
            print(f"| {name} | {t[len(t) // 2]:.1f} / {t[-1]:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
