"""A way out of the planners' local minima: after ``patience`` moves that brought the rope's best error down by
under ``min_gain``, take the greedy move (the node farthest from its place dragged towards it: the greedy planner's
``diffdlo.tasks.task.greedy_action``) until the rope is ``min_gain`` below its best error before the stall, then
hand back to the planner.

Why: on a route a one-move planner can stall in a local minimum of its cost (the rope caught behind a peg, every
single move that frees it raising the error first), while greedy, blind to the cost, walks through it; the grid's
misses of CEM and the gradient planner are such stalls (docs/ROUTING.md). The error is the one the planner is given
(the rope against the target on the board, or centroid-aligned off a route), so an episode from pictures stays one
from pictures.
"""
from __future__ import annotations

import torch

from diffdlo.tasks.task import greedy_action, greedy_drags


def stalled(errors: list[float], window: int, min_gain: float) -> bool:
    """Whether the last ``window`` errors brought the best of those before them down by less than ``min_gain``
    (False while there are no errors before the window)."""
    return len(errors) > window and min(errors[:-window]) - min(errors[-window:]) < min_gain


class StallEscape:
    def __init__(self, sim, patience: int, pin: bool = False, min_gain: float = 1e-3):
        if patience < 1:
            raise ValueError(f"--escape must be >= 1 to escape (0: off), got {patience}")
        self.patience, self.min_gain = int(patience), float(min_gain)
        self.p, self.pin = sim.params, bool(pin)
        self.reset()

    def reset(self) -> None:
        self.errors: list[float] = []       # the rope's error when each move was planned
        self.escaping_below: float | None = None
        self.escapes, self.moves = 0, 0

    def plan(self, pos: torch.Tensor, target: torch.Tensor, pegs: torch.Tensor | None = None) -> torch.Tensor | None:
        """The greedy action while escaping a stall, else None (the planner plans)."""
        _, dist = greedy_drags(pos, target, self.p.max_disp, align=pegs is None)
        error = float(dist.mean())
        self.errors.append(error)
        if self.escaping_below is not None and error < self.escaping_below:
            self.escaping_below, self.errors = None, [error]            # out: the planner again, a fresh window
        elif self.escaping_below is None and stalled(self.errors, self.patience, self.min_gain):
            self.escaping_below = min(self.errors) - self.min_gain
            self.escapes += 1
        if self.escaping_below is None:
            return None
        self.moves += 1
        return greedy_action(pos, target, self.p, self.pin, align=pegs is None)
