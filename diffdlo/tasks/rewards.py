"""Rewards (thesis eq 2.7-2.11) and task metrics, batched: rope (B, N, 2), target (N, 2) or (B, N, 2)."""
from __future__ import annotations

import math

import torch

from .routing import route_cost


def abs_diff(pos: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """(B,) eq 2.7 sum_i |x_i - y_i| (Euclidean distance per node, absolute positions)."""
    return (pos - target).norm(dim=-1).sum(-1)


def reward_abs_diff(pos: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """(B,) eq 2.7: R = -sum_i |x_i - y_i|."""
    return -abs_diff(pos, target)


def reward_delta_gain(prev_pos: torch.Tensor, pos: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """(B,) eq 2.8: R = sum_i |x_{i,t-1} - y_i| - sum_i |x_{i,t} - y_i| (positive when the move helped)."""
    return abs_diff(prev_pos, target) - abs_diff(pos, target)


def pairwise_shape_term(pos: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """(B,) eq 2.10: P = sum_j sum_i | ||x_j - x_i|| - ||y_j - y_i|| | over all ordered pairs."""
    target = target.expand_as(pos)
    return (_pair_distances(pos) - _pair_distances(target)).abs().sum((-1, -2))


def _pair_distances(pos: torch.Tensor) -> torch.Tensor:
    # Differentiable at coincident nodes (the diagonal): norm's gradient at 0 is NaN, so add 0 there explicitly.
    diff = pos.unsqueeze(-2) - pos.unsqueeze(-3)
    sq = (diff * diff).sum(-1)
    eye = torch.eye(pos.shape[-2], dtype=torch.bool, device=pos.device)
    return torch.where(eye, torch.zeros_like(sq), sq.masked_fill(eye, 1.0).sqrt())


def end_to_end_angle(pos: torch.Tensor) -> torch.Tensor:
    """(B,) eq 2.11's angle atan2(y_0 - y_n, x_0 - x_n) of the line from the last node to the first."""
    d = pos[..., 0, :] - pos[..., -1, :]
    return torch.atan2(d[..., 1], d[..., 0])


def orientation_error(pos: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """(B,) eq 2.11 O: difference of the end-to-end angles, wrapped to [0, pi] (the printed form is not)."""
    diff = end_to_end_angle(pos) - end_to_end_angle(target.expand_as(pos))
    return torch.remainder(diff + math.pi, 2 * math.pi).sub(math.pi).abs()


def reward_position_orientation(pos: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """(B,) eq 2.9: reward = -P - O."""
    return -pairwise_shape_term(pos, target) - orientation_error(pos, target)


def node_errors(pos: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """(B, N) each node's distance [m] to its place in the target after aligning the centroids of rope and target
    (node i against target node i): the per-node figure ``shape_error`` averages and ``worst_node_error`` maxes."""
    target = target.expand_as(pos)
    a = pos - pos.mean(dim=-2, keepdim=True)
    b = target - target.mean(dim=-2, keepdim=True)
    return (a - b).norm(dim=-1)


def shape_error(pos: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """(B,) mean node distance [m] between rope and target after aligning their centroids.

    Translation-free, orientation-sensitive; node i is compared with target node i.
    """
    return node_errors(pos, target).mean(-1)


def worst_node_error(pos: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """(B,) the largest node distance [m] between rope and target after aligning their centroids (the alignment of
    ``shape_error``, the max over nodes in place of the mean): how far the worst-placed node, e.g. a hooked end, is
    from its place. Never below shape_error; equal to it when every node is equally far (a rigid shift: 0 for
    both)."""
    return node_errors(pos, target).amax(-1)


def within_tolerance(mean_error, worst_error, tol: float, worst_tol: float | None = None):
    """The task's success test on errors already measured: mean_error < tol and, when ``worst_tol`` is given,
    worst_error < worst_tol. Tensors (B,) give a bool tensor, floats a bool; ``worst_error`` is not read when
    ``worst_tol`` is None (it may be None then). The env (``diffdlo.tasks.task``) and the comparison's tolerance helper
    (``benchmarks.compare.stats.success_move``) both test with it."""
    ok = mean_error < tol
    if worst_tol is not None:
        ok = ok & (worst_error < worst_tol)
    return ok


def reward_shape_gain(prev_pos: torch.Tensor, pos: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """(B,) ours, not the thesis's: 100 x (shape_error before - after) [m], i.e. the centimetres of shape error the
    move removed. It measures progress in the success metric itself (translation-free, orientation-sensitive), so
    an episode's undiscounted return telescopes to the error removed (in cm): no reward for drifting or for ending
    an episode, and O(1) per move (a good move removes ~1-2 cm) without normalization."""
    return 100.0 * (shape_error(prev_pos, target) - shape_error(pos, target))


def is_success(pos: torch.Tensor, target: torch.Tensor, tol: float = 0.01,
               worst_tol: float | None = None) -> torch.Tensor:
    """(B,) bool: shape_error < tol (default 1 cm, 2% of the rope length, params/cable.yaml's success_tol) and, when
    ``worst_tol`` is given, worst_node_error < worst_tol (``within_tolerance``). The env reads its tolerances from
    its options (``EnvOptions.success_tol``, ``success_worst_tol``), not from this default."""
    errors = node_errors(pos, target)
    return within_tolerance(errors.mean(-1), errors.amax(-1), tol, worst_tol)


def reward_route_gain(prev_pos: torch.Tensor, pos: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """(B,) ours, for routes (diffdlo/tasks/routing.py): 100 x (mean node distance to the target before - after) [cm],
    on the board (no centroid alignment: the pegs fix where the route lies). eq 2.8's delta_gain per node in cm."""
    return 100.0 * ((prev_pos - target).norm(dim=-1).mean(-1) - (pos - target).norm(dim=-1).mean(-1))


def reward_route_side_gain(prev_pos: torch.Tensor, pos: torch.Tensor, target: torch.Tensor,
                           pegs: torch.Tensor) -> torch.Tensor:
    """(B,) ours, for routes: 100 x (route cost before - after) [cm], the route cost being the planners'
    (``diffdlo.tasks.routing.route_cost``: the mean node distance on the board plus SIDE_COST = 5 cm per peg passed on
    the wrong side). route_gain plus 5 for each peg a move brings to the route's side (minus 5 for each it takes off):
    a shaping of the success test's side condition by a potential (Ng et al. 1999), so a policy is paid for the
    side before it is within 1 cm."""
    return 100.0 * (route_cost(prev_pos, target, pegs) - route_cost(pos, target, pegs))


REWARDS = ("position_orientation", "abs_diff", "delta_gain", "shape_gain", "route_gain", "route_side_gain")
# The rewards that see where the rope lies on the board (the others align centroids or compare shapes only): the
# ones a route can be scored by.
BOARD_REWARDS = ("abs_diff", "delta_gain", "route_gain", "route_side_gain")
# The rewards that need the pegs (a route only)
PEG_REWARDS = ("route_side_gain",)


def reward(kind: str, prev_pos: torch.Tensor, pos: torch.Tensor, target: torch.Tensor,
           pegs: torch.Tensor | None = None) -> torch.Tensor:
    """(B,) the reward named ``kind`` (one of REWARDS) for the move prev_pos -> pos (``pegs`` (B, K, 3): a route's,
    which "route_side_gain" needs)."""
    if kind == "route_side_gain":
        if pegs is None:
            raise ValueError("reward 'route_side_gain' scores the pegs' sides: it needs a route's pegs")
        return reward_route_side_gain(prev_pos, pos, target, pegs)
    if kind == "position_orientation":
        return reward_position_orientation(pos, target)
    if kind == "abs_diff":
        return reward_abs_diff(pos, target)
    if kind == "delta_gain":
        return reward_delta_gain(prev_pos, pos, target)
    if kind == "shape_gain":
        return reward_shape_gain(prev_pos, pos, target)
    if kind == "route_gain":
        return reward_route_gain(prev_pos, pos, target)
    raise ValueError(f"unknown reward {kind!r}: use one of {list(REWARDS)}")
