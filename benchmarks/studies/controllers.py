"""Kinematic drag vs the thesis's PID, and how far ropes are from rest when the settle cap stops them.

    python benchmarks/studies/controllers.py [--batch 32] [--seed 0]

Prints, for each controller: the grasped node's distance from its goal at release, the substeps per move, the
share of ropes that met the 5e-5 m/s threshold, and the wall time of the batched move. Then, for the default
controller, how much farther the ropes would still creep if the settle ran 10 s instead of the cap.
"""
from __future__ import annotations

import argparse
import dataclasses
import time

import torch

import diffdlo
from diffdlo.planar import control


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    base = diffdlo.load_params("cable")
    g = torch.Generator().manual_seed(args.seed)
    pos = diffdlo.random_shape(args.batch, base, g, dtype=torch.float64)
    node = torch.randint(0, base.n_nodes, (args.batch,), generator=g)
    delta = control.clip_drag((torch.rand(args.batch, 2, generator=g, dtype=torch.float64) * 2 - 1)
                              * base.action_scale, base.max_disp)
    rows = [f"{'controller':<10} {'goal err median/max [mm]':>25} {'substeps mean':>14} {'settled':>8} {'wall+rec [s]':>12}"]
    for controller in ("kinematic", "pid"):
        p = dataclasses.replace(base, controller=controller)
        sim = diffdlo.Simulator(p, dtype=torch.float64)
        t0 = time.perf_counter()
        _, info = sim.move(pos, node, delta, return_info=True, record_every=1)
        wall = time.perf_counter() - t0
        idx = info.drag_substeps
        at_release = info.frames[idx, torch.arange(args.batch), node]
        err = (at_release - (pos[torch.arange(args.batch), node] + delta)).norm(dim=-1) * 1000
        rows.append(f"{controller:<10} {err.median():>12.1f} / {err.max():<10.1f} "
                    f"{info.substeps.double().mean():>14.0f} {info.settled.double().mean():>8.0%} {wall:>12.2f}")
    print("\n".join(rows))

    long = dataclasses.replace(base, settle_max_substeps=10_000)
    sim = diffdlo.Simulator(long, dtype=torch.float64)
    capped = diffdlo.Simulator(base, dtype=torch.float64).move(pos, node, delta)
    rested, info = sim.move(pos, node, delta, return_info=True)
    creep = (rested - capped).norm(dim=-1).amax(-1) * 1000
    print(f"settle cap {base.settle_max_substeps} substeps vs 10 s: the fastest node would still move "
          f"median {creep.median():.1f} mm, max {creep.max():.1f} mm; settled within 10 s: "
          f"{info.settled.double().mean():.0%}")


if __name__ == "__main__":
    main()
