"""What the settle cap does to precision: how far a rope still moves after the move that "ended" it.

    python -m benchmarks.studies.precision_limits [--ropes 64] [--seed 0] [--out runs/precision_limits]

A move ends when the fastest node is slower than settle_threshold (5e-5 m/s, checked every 100 substeps) or after
settle_max_substeps (1 s, params/cable.yaml: our cap, not the thesis's). The next move starts the rope at rest
where the move left it, so in the simulation the cap is part of the dynamics and costs no precision by itself; but
a rope the cap stopped was still moving, so a real cable would go on. This measures by how much, in the regime the
precise task ends in: ropes near a straight target (a straight rope in a random direction, bent by a random walk of
its link angles of step --sigma, so its mean node error is a few millimetres), then one greedy move (the node
farthest from its place dragged towards it, diffdlo.tasks.task.greedy_drags), as the last moves of an episode are.

For each rope: the shape error after the move, whether the cap (not the threshold) ended it, and the mean and worst
node displacement (centroids aligned, as the task's errors) between the state the move returned and the state after
1, 5 and 30 s more of free evolution from rest. Prints a table (median and 95th percentile over the ropes) and
writes <out>/results.json when --out is given.
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import torch

from diffdlo.tasks import task
from diffdlo.planar.params import ParamsError, load_params
from diffdlo.tasks.rewards import node_errors
from diffdlo.planar.simulator import Simulator
from diffdlo.utils.files import OutBusyError, check_fresh_out, out_lock, write_json_atomic

RELAX_SECONDS = (1.0, 5.0, 30.0)


def near_target_ropes(sim: Simulator, ropes: int, sigma: float, generator: torch.Generator):
    """(rope, target) pairs, each (B, N, 2): straight targets in random directions and ropes bent off them by a
    random walk of their link angles (step ``sigma`` rad), centred at the origin."""
    p = sim.params
    n = p.n_nodes
    heading = (torch.rand(ropes, 1, generator=generator, dtype=torch.float64) * 2 - 1) * math.pi
    bend = torch.cumsum(sigma * torch.randn(ropes, n - 1, generator=generator, dtype=torch.float64), dim=1)
    bend = bend - bend.mean(1, keepdim=True)               # keeps the rope's mean direction on the target's
    link = p.rest_length

    def chain(angles: torch.Tensor) -> torch.Tensor:
        steps = link * torch.stack([angles.cos(), angles.sin()], -1)
        pos = torch.cat([torch.zeros(ropes, 1, 2, dtype=torch.float64), steps.cumsum(1)], 1)
        return pos - pos.mean(1, keepdim=True)

    target = chain(heading.expand(ropes, n - 1))
    rope = chain(heading + bend)
    return rope.to(sim.device, sim.dtype), target.to(sim.device, sim.dtype)


def percentiles(x: torch.Tensor) -> dict[str, float]:
    x = x.double().cpu()
    return {"median": float(x.median()), "p95": float(torch.quantile(x, 0.95)), "max": float(x.max())}


def measure(ropes: int = 64, seed: int = 0, sigma: float = 0.05, params: str = "cable") -> dict:
    p = load_params(params)
    sim = Simulator(p, dtype=torch.float64)
    g = torch.Generator().manual_seed(seed)
    rope, target = near_target_ropes(sim, ropes, sigma, g)
    drags, gaps = task.greedy_drags(rope, target, p.max_disp)
    node = gaps.argmax(-1)
    drag = drags[torch.arange(ropes), node]
    moved, info = sim.move(rope, node, drag, return_info=True)
    before = node_errors(rope, target)
    after = node_errors(moved, target)
    out = {"ropes": ropes, "seed": seed, "sigma": sigma, "params": params,
           "settle_threshold": p.settle_threshold, "settle_max_substeps": p.settle_max_substeps, "dt": p.dt,
           "error_before": percentiles(before.mean(-1)), "error_after": percentiles(after.mean(-1)),
           "worst_after": percentiles(after.amax(-1)),
           "stopped_by_cap": float((~info.settled).double().mean()), "relax": []}
    pos, vel, done = moved, None, 0
    for seconds in RELAX_SECONDS:
        substeps = int(round(seconds / p.dt))
        pos, vel = sim.integrate(pos, vel, substeps - done)
        done = substeps
        drift = node_errors(pos, moved)                    # centroids aligned: the change of shape
        err = node_errors(pos, target)
        out["relax"].append({"seconds": seconds, "drift_mean": percentiles(drift.mean(-1)),
                             "drift_worst": percentiles(drift.amax(-1)),
                             "error_mean": percentiles(err.mean(-1)), "error_worst": percentiles(err.amax(-1))})
    return out


def table(res: dict) -> str:
    mm = 1e3
    rows = [f"ropes {res['ropes']} near a straight target (link-angle walk sigma {res['sigma']} rad), one greedy move; "
            f"the cap ended {res['stopped_by_cap'] * 100:.0f} % of the moves",
            f"error after the move [mm]: mean {res['error_after']['median'] * mm:.2f} (median), "
            f"{res['error_after']['p95'] * mm:.2f} (95th pct); worst node {res['worst_after']['median'] * mm:.2f}, "
            f"{res['worst_after']['p95'] * mm:.2f}",
            "", "| relaxing on for | shape change, mean node [mm] (median / 95th) | worst node [mm] (median / 95th) | "
            "error to target, mean [mm] (median / 95th) |", "|---|---|---|---|"]
    for r in res["relax"]:
        rows.append(f"| {r['seconds']:g} s | {r['drift_mean']['median'] * mm:.3f} / {r['drift_mean']['p95'] * mm:.3f} | "
                    f"{r['drift_worst']['median'] * mm:.3f} / {r['drift_worst']['p95'] * mm:.3f} | "
                    f"{r['error_mean']['median'] * mm:.2f} / {r['error_mean']['p95'] * mm:.2f} |")
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.studies.precision_limits",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--ropes", type=int, default=64)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--sigma", type=float, default=0.05, help="step of the ropes' link-angle walk [rad]")
    ap.add_argument("--params", default="cable")
    ap.add_argument("--out", type=Path, help="folder for results.json")
    ap.add_argument("--overwrite", action="store_true", help="replace an existing results.json in --out")
    args = ap.parse_args(argv)
    if args.ropes < 1:
        ap.error(f"--ropes must be at least 1, got {args.ropes}")
    if not (math.isfinite(args.sigma) and args.sigma > 0):
        ap.error(f"--sigma must be a positive number, got {args.sigma}")
    try:
        if args.out is not None:
            check_fresh_out(args.out, args.overwrite, what="a precision_limits run")
        res = measure(args.ropes, args.seed, args.sigma, args.params)
    except (ParamsError, OutBusyError, FileExistsError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(table(res))
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        with out_lock(args.out):
            write_json_atomic(args.out / "results.json", res)
        print(f"wrote {args.out / 'results.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
