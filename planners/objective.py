"""The planning objective: cost of B candidate action sequences from one start state.

``SimObjective(sim, start, target)(actions (B, H, 3)) -> (B,)`` rolls the B sequences out with ONE batched
``Simulator.move`` per horizon step and returns the ``shape_error`` [m] (centroid-aligned mean node distance, the
metric that defines success in the env) after the last move. Actions are the env's node actions in [0, 1]^3, clipped
to [0, 1] and decoded by the env's own rule (``diffdlo.task.decode_node_action``, eq 2.6), so a plan can be executed
in the env as is. Planners only need ``objective(actions) -> costs``: the CEM optimizer is generic
and can later be given a learned latent model's objective instead (PlaNet).

Why shape_error and not the env's default reward (eq 2.9-2.11, pairwise distances + end-to-end angle): the task's
success test is shape_error < success_tol, it is in metres (readable), smooth almost everywhere, and is what the
gradient planner backpropagates; every planner here (CEM, gradient, greedy) optimises or greedily reduces the same
quantity. ``running_weight`` > 0 adds that weight times the mean error of the intermediate states (H > 1 only),
which prefers plans that improve early (useful in receding-horizon control, where only the first move is kept).
"""
from __future__ import annotations

from typing import Callable

import torch

from diffdlo.rewards import shape_error
from diffdlo.task import decode_node_action
from diffdlo.simulator import Simulator


def sequence_cost(states: list[torch.Tensor], target: torch.Tensor, running_weight: float = 0.0) -> torch.Tensor:
    """The planners' cost of a rolled-out sequence: shape_error after the last of the H states (each (..., N, 2)),
    plus ``running_weight`` times the mean error of the H - 1 intermediate ones. Shared by the simulator's objective
    and a learned model's (agents/models/ensemble.py), so both plan for the same thing."""
    cost = shape_error(states[-1], target)
    if len(states) > 1 and running_weight > 0:
        cost = cost + running_weight * sum(shape_error(s, target) for s in states[:-1]) / (len(states) - 1)
    return cost


class SimObjective:
    """cost(actions (B, H, 3)) -> (B,) shape_error after rolling the sequences out from ``start`` (N, 2).

    ``sim_evals`` counts the rope-moves simulated (forward), ``calls`` the batched calls. Differentiable with
    respect to the drag part of the actions (use ``rollout_deltas`` for node ids + drags directly).
    """

    def __init__(self, sim: Simulator, start: torch.Tensor, target: torch.Tensor, running_weight: float = 0.0):
        self.sim, self.p = sim, sim.params
        self.start = start.detach().to(device=sim.device, dtype=sim.dtype)
        self.target = target.detach().to(device=sim.device, dtype=sim.dtype)
        self.running_weight = float(running_weight)
        self.sim_evals = 0
        self.calls = 0

    def rollout_deltas(self, node: torch.Tensor, delta: torch.Tensor, return_states: bool = False):
        """node (B, H) int64, delta (B, H, 2) [m] -> cost (B,) (and the states (B, H, N, 2) after each move)."""
        b, h = node.shape
        pos = self.start.expand(b, *self.start.shape).contiguous()
        states = []
        for t in range(h):
            pos = self.sim.move(pos, node[:, t].to(self.sim.device), delta[:, t].to(self.sim.dtype))
            self.sim_evals += b
            self.calls += 1
            states.append(pos)
        cost = sequence_cost(states, self.target, self.running_weight)
        return (cost, torch.stack(states, 1)) if return_states else cost

    def __call__(self, actions: torch.Tensor) -> torch.Tensor:
        if actions.ndim != 3 or actions.shape[-1] != 3:
            raise ValueError(f"actions must have shape (B, H, 3), got {tuple(actions.shape)}")
        node, delta = decode_node_action(actions.to(device=self.sim.device, dtype=self.sim.dtype), self.p)
        return self.rollout_deltas(node, delta)


Objective = Callable[[torch.Tensor], torch.Tensor]
