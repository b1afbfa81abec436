"""Wall time of one move() (drag + settle) of the default simulator at several batch sizes.

    python benchmarks/move_time.py [--batches 1 64] [--repeats 3] [--device cpu] [--dtype float32]

Random shapes and random actions (seeded); reports the median of the repeats, substeps per move and
rope-substeps per second. Threads: torch's default (the machine's cores).
"""
from __future__ import annotations

import argparse
import json
import statistics
import time

import torch

import diffdlo


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 64])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    args = parser.parse_args()
    p = diffdlo.load_params("cable")
    sim = diffdlo.Simulator(p, device=args.device, dtype=getattr(torch, args.dtype))
    results = []
    print(f"{'B':>6} {'move [s]':>9} {'substeps':>9} {'rope-substeps/s':>16} {'moves/s':>9}")
    for batch in args.batches:
        g = torch.Generator().manual_seed(0)
        pos = sim.random_shape(batch, g)
        node = torch.randint(0, p.n_nodes, (batch,), generator=g).to(sim.device)
        delta = ((torch.rand(batch, 2, generator=g) * 2 - 1) * p.action_scale).to(sim.device, sim.dtype)
        times = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            _, info = sim.move(pos, node, delta, return_info=True)
            if sim.device.type == "cuda":
                torch.cuda.synchronize()
            times.append(time.perf_counter() - t0)
        wall = statistics.median(times)
        loop_steps = int(info.substeps.max())
        row = {"batch": batch, "move_s": wall, "substeps": loop_steps,
               "rope_substeps_per_s": batch * loop_steps / wall, "moves_per_s": batch / wall}
        results.append(row)
        print(f"{batch:>6} {wall:>9.3f} {loop_steps:>9} {row['rope_substeps_per_s']:>16.0f} {row['moves_per_s']:>9.2f}")
    print(json.dumps({"device": str(sim.device), "dtype": args.dtype, "results": results}))


if __name__ == "__main__":
    main()
