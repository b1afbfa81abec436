"""A short simulation that writes pictures of a rope being dragged: python -m diffdlo.tasks.demo --out runs/demo"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

import diffdlo
from diffdlo.utils import render
from diffdlo.tasks.task import greedy_drags


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", default="runs/demo", help="output folder (default: runs/demo)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--moves", type=int, default=7)
    args = parser.parse_args(argv)

    sim = diffdlo.Simulator(diffdlo.load_params("cable"), device=args.device)
    target = sim.target_shape("horizontal")
    pos = sim.random_shape(1, torch.Generator().manual_seed(args.seed))
    start = pos
    # The greedy move, a few times: drag the node farthest from its place in the (centroid-aligned) target
    # towards it, at most 10 cm.
    frames, titles, snapshots = [], ["start"], [pos[0]]
    t0 = time.perf_counter()
    for i in range(args.moves):
        drags, dist = greedy_drags(pos, target, 0.1)
        node = dist.argmax(dim=-1)
        delta = drags[0, node]
        pos, info = sim.move(pos, node, delta, return_info=True, record_every=50)
        frames.append(info.frames[:, 0])
        snapshots.append(pos[0])
        titles.append(f"move {i + 1}: node {int(node)}, error {diffdlo.shape_error(pos, target).item() * 100:.1f} cm")
    wall = time.perf_counter() - t0
    out = Path(args.out)
    png = out / "demo.png"
    render.plot_ropes(torch.stack(snapshots), target, png, titles=titles, cols=4)
    gif = render.save_gif(torch.cat(frames), out / "demo.gif", target, title="drag")
    print(f"{args.moves} moves in {wall:.2f} s; shape error {diffdlo.shape_error(start, target).item() * 100:.1f} cm -> "
          f"{diffdlo.shape_error(pos, target).item() * 100:.1f} cm; wrote {png} and {gif}")


if __name__ == "__main__":
    main()
