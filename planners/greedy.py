"""Greedy baseline: grasp the node farthest from its place in the centroid-aligned target and drag it towards that
place (at most max_disp = 0.1 m). No simulation: sim_evals = 0.

    python -m planners.greedy --target diagonal --max-steps 40
"""
from __future__ import annotations

import argparse

import torch

from .objective import encode_node_actions


class GreedyPlanner:
    name = "greedy"

    def __init__(self, sim):
        self.sim, self.p = sim, sim.params
        self.sim_evals = 0

    def reset(self) -> None:
        pass

    def plan(self, pos: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        aligned = target - target.mean(0) + pos.mean(0)
        gap = aligned - pos                                           # (N, 2)
        dist = gap.norm(dim=-1)
        node = dist.argmax()
        scale = (self.p.max_disp / dist[node].clamp_min(1e-12)).clamp(max=1.0)
        return encode_node_actions(node, gap[node] * scale, self.p)

    @staticmethod
    def add_args(parser: argparse.ArgumentParser) -> None:
        pass

    @classmethod
    def from_args(cls, sim, args) -> "GreedyPlanner":
        return cls(sim)


def main(argv: list[str] | None = None) -> int:
    from .common import run_cli
    return run_cli(GreedyPlanner, "greedy", __doc__, argv)


if __name__ == "__main__":
    raise SystemExit(main())
