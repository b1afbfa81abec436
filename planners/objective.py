"""The planning objective: cost of B candidate action sequences from one start state.

``SimObjective(sim, start, target)(actions (B, H, 3)) -> (B,)`` rolls the B sequences out with ONE batched
``Simulator.move`` per horizon step and returns the ``shape_error`` [m] (centroid-aligned mean node distance, the
metric that defines success in the env) after the last move. Actions are the env's node actions in [0, 1]^3, clipped
to [0, 1] and decoded by the env's own rule (``diffdlo.tasks.task.decode_node_action``, eq 2.6), so a plan can be
executed in the env as is. Planners only need ``objective(actions) -> costs``: the CEM optimizer is generic
and can later be given a learned latent model's objective instead (PlaNet).

Why shape_error and not the env's default reward (eq 2.9-2.11, pairwise distances + end-to-end angle): the task's
success test is shape_error < success_tol, it is in metres (readable), smooth almost everywhere, and is what the
gradient planner backpropagates; every planner here (CEM, gradient, greedy) optimises or greedily reduces the same
quantity. ``running_weight`` > 0 adds that weight times the mean error of the intermediate states (H > 1 only),
which prefers plans that improve early (useful in receding-horizon control, where only the first move is kept).

A route among pegs (``pegs`` given, diffdlo/tasks/routing.py): the moves run with the pegs, the error is measured on the
board (no centroid alignment: the success test's), and every peg passed on the wrong side costs ``SIDE_COST`` [m]
more (the side test is discrete: it steers CEM and greedy, and gives a gradient nothing). Actions of 4 entries are
the env's "node_pin" actions: the last one a second gripper's node (diffdlo.tasks.task.decode_pin).
"""
from __future__ import annotations

from typing import Callable

import torch

from diffdlo.tasks import routing
from diffdlo.tasks.rewards import shape_error
from diffdlo.tasks.task import decode_node_action, decode_pin
from diffdlo.planar.simulator import Simulator

# A route's cost (the error on the board plus SIDE_COST per peg on the wrong side) is the routing task's own rule:
# diffdlo.tasks.routing holds it, so the env's reward "route_side_gain" and the planners score the same thing.
SIDE_COST = routing.SIDE_COST
route_cost = routing.route_cost


def sequence_cost(states: list[torch.Tensor], target: torch.Tensor, running_weight: float = 0.0,
                  pegs: torch.Tensor | None = None) -> torch.Tensor:
    """The planners' cost of a rolled-out sequence: shape_error after the last of the H states (each (..., N, 2)),
    plus ``running_weight`` times the mean error of the H - 1 intermediate ones (a route, ``pegs`` (K, 3) given:
    ``route_cost`` in place of shape_error). Shared by the simulator's objective and a learned model's
    (agents/models/ensemble.py), so both plan for the same thing."""
    error = shape_error if pegs is None else (lambda s, t: route_cost(s, t, pegs))
    cost = error(states[-1], target)
    if len(states) > 1 and running_weight > 0:
        cost = cost + running_weight * sum(error(s, target) for s in states[:-1]) / (len(states) - 1)
    return cost


class SimObjective:
    """cost(actions (B, H, 3 or 4)) -> (B,) shape_error (a route's ``route_cost``) after rolling the sequences out
    from ``start`` (N, 2), with ``pegs`` (K, 3) on the table where given.

    ``sim_evals`` counts the rope-moves simulated (forward), ``calls`` the batched calls. Differentiable with
    respect to the drag part of the actions (use ``rollout_deltas`` for node ids + drags directly).
    """

    def __init__(self, sim: Simulator, start: torch.Tensor, target: torch.Tensor, running_weight: float = 0.0,
                 pegs: torch.Tensor | None = None):
        self.sim, self.p = sim, sim.params
        self.start = start.detach().to(device=sim.device, dtype=sim.dtype)
        self.target = target.detach().to(device=sim.device, dtype=sim.dtype)
        self.pegs = None if pegs is None else pegs.detach().to(device=sim.device, dtype=sim.dtype)
        self.running_weight = float(running_weight)
        self.sim_evals = 0
        self.calls = 0

    def rollout_deltas(self, node: torch.Tensor, delta: torch.Tensor, return_states: bool = False,
                       pin: torch.Tensor | None = None):
        """node (B, H) int64, delta (B, H, 2) [m], pin (B, H) int64 or None -> cost (B,) (and the states
        (B, H, N, 2) after each move)."""
        b, h = node.shape
        pos = self.start.expand(b, *self.start.shape).contiguous()
        states = []
        for t in range(h):
            pos = self.sim.move(pos, node[:, t].to(self.sim.device), delta[:, t].to(self.sim.dtype), self.pegs,
                                None if pin is None else pin[:, t].to(self.sim.device))
            self.sim_evals += b
            self.calls += 1
            states.append(pos)
        cost = sequence_cost(states, self.target, self.running_weight, self.pegs)
        return (cost, torch.stack(states, 1)) if return_states else cost

    def __call__(self, actions: torch.Tensor) -> torch.Tensor:
        if actions.ndim != 3 or actions.shape[-1] not in (3, 4):
            raise ValueError(f"actions must have shape (B, H, 3) (node actions) or (B, H, 4) (node_pin), got "
                             f"{tuple(actions.shape)}")
        a = actions.to(device=self.sim.device, dtype=self.sim.dtype)
        node, delta = decode_node_action(a[..., :3], self.p)
        pin = decode_pin(a[..., 3], node, self.p.n_nodes) if a.shape[-1] == 4 else None
        return self.rollout_deltas(node, delta, pin=pin)


Objective = Callable[[torch.Tensor], torch.Tensor]
