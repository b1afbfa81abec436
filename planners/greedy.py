"""Greedy baseline: grasp the node farthest from its place in the centroid-aligned target and drag it towards that
place (at most max_disp = 0.1 m). No simulation: sim_evals = 0.

    python -m planners.greedy --target diagonal --max-steps 40
"""
from __future__ import annotations

import torch

from diffdlo.task import encode_node_action, greedy_drags


class GreedyPlanner:
    name = "greedy"

    def __init__(self, sim, seed: int = 0):       # deterministic: the seed changes nothing
        self.sim, self.p = sim, sim.params
        self.sim_evals = 0

    def reset(self, seed: int | None = None) -> None:    # deterministic: nothing to re-seed
        pass

    def plan(self, pos: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        drags, dist = greedy_drags(pos, target, self.p.max_disp)
        node = dist.argmax()
        return encode_node_action(node, drags[node], self.p.n_nodes, self.p.action_scale)

    OPTIONS: dict = {}            # nothing to set on the command line


def main(argv: list[str] | None = None) -> int:
    from .common import run_cli
    return run_cli(GreedyPlanner, "greedy", __doc__, argv)


if __name__ == "__main__":
    raise SystemExit(main())
