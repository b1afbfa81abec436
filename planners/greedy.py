"""Greedy baseline: grasp the node farthest from its place in the centroid-aligned target (a route's: on the board)
and drag it towards that place (at most max_disp = 0.1 m); with ``--pin 1`` a second gripper holds the node, two or
more links from the grasped one, that is nearest its place. No simulation: sim_evals = 0.

    python -m planners.greedy --target diagonal --max-steps 40
    python -m planners.greedy --target route:u_two_pegs --pin 1 --max-steps 40
"""
from __future__ import annotations

import torch

from diffdlo.tasks.task import greedy_action

from .common import run_cli


class GreedyPlanner:
    name = "greedy"

    def __init__(self, sim, seed: int = 0, pin: int = 0):       # deterministic: the seed changes nothing
        self.sim, self.p = sim, sim.params
        self.pin = bool(pin)
        self.sim_evals = 0

    def reset(self, seed: int | None = None) -> None:    # deterministic: nothing to re-seed
        pass

    def plan(self, pos: torch.Tensor, target: torch.Tensor, pegs: torch.Tensor | None = None) -> torch.Tensor:
        return greedy_action(pos, target, self.p, self.pin, align=pegs is None)

    # the command line's options (planners/common.py): constructor argument -> (type, default, allowed, help)
    OPTIONS = {"pin": (int, 0, "[0, 1]", "1: a second gripper holds the best-placed node (node_pin actions)")}


def main(argv: list[str] | None = None) -> int:
    return run_cli(GreedyPlanner, "greedy", __doc__, argv)


if __name__ == "__main__":
    raise SystemExit(main())
