"""Ropes among pegs: the pictures of the routing task (docs/ROUTING.md) that the perception reads there.

``board_shapes`` draws ropes on random boards (``diffdlo.tasks.routing.random_layout``) as the routing env shows them:
its starts beside and across the board, settled among the pegs (the env's own ``routing.start_beside`` /
``start_across``), ropes after random moves among the pegs, and ropes lying on the route near its pegs, as at the end
of an episode. The fine-tuning (``python -m diffdlo.perception --pegs-share``) and the measurement
(benchmarks/studies/perception_pegs.py) draw from it with different seeds.
"""
from __future__ import annotations

import torch

from ..tasks import routing
from ..planar.params import CableParams

BOARD_KINDS = ("beside", "across", "moved", "on_route")
MAX_PEGS = 4            # the routing env's default peg slots (EnvOptions.max_pegs); random boards hold 2-4
NEAR_DRAG = 0.04        # [m] per-axis drag of the small moves that take an "on_route" rope off its route


def board_shapes(n: int, p: CableParams, generator: torch.Generator, sim, kind: str, max_moves: int = 8,
                 slots: int = MAX_PEGS) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``n`` ropes of ``kind`` on ``n`` random boards -> ropes (n, N, 2), pegs (n, slots, 3) (rows of zeros past a
    board's pegs, as the env's observation) and routes (n, N, 2), float64, in the board's frame (not moved).

    kind: "beside" / "across" the env's route starts (``route_start``), settled among the pegs; "moved" an "across"
    start after 1..``max_moves`` random moves (random node, drag uniform in the action box) among the pegs;
    "on_route" the route itself settled among its pegs, then 1-3 small moves (drag uniform in +-NEAR_DRAG per axis).
    ``sim``: a Simulator of ``p``. Drawn from ``generator`` alone (same seed, same ropes)."""
    if kind not in BOARD_KINDS:
        raise ValueError(f"kind must be one of {list(BOARD_KINDS)}, got {kind!r}")
    if not isinstance(n, int) or n < 1:
        raise ValueError(f"n must be a positive integer, got {n!r}")
    layouts = [routing.random_layout(p, generator) for _ in range(n)]
    pegs = torch.stack([routing.padded(lay.pegs.to(torch.float64), slots) for lay in layouts])
    routes = torch.stack([lay.route.to(torch.float64) for lay in layouts])
    if kind == "on_route":
        ropes = routes.clone()
    else:
        start = routing.start_beside if kind == "beside" else routing.start_across
        ropes = torch.stack([start(lay, p, generator) for lay in layouts])
    sim_pegs = pegs.to(sim.dtype)
    ropes = sim.settle(ropes.to(sim.dtype), pegs=sim_pegs).double()
    if kind in ("moved", "on_route"):
        most, scale = (max_moves, p.action_scale) if kind == "moved" else (3, NEAR_DRAG)
        moves = torch.randint(1, most + 1, (n,), generator=generator)
        for k in range(most):
            node = torch.randint(0, p.n_nodes, (n,), generator=generator)
            delta = (torch.rand(n, 2, generator=generator, dtype=torch.float64) * 2 - 1) * scale
            delta = delta * (moves > k).unsqueeze(-1)
            ropes = sim.move(ropes.to(sim.dtype), node, delta.to(sim.dtype), sim_pegs).double()
    return ropes, pegs, routes
