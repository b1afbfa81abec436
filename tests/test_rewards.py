"""Rewards eq 2.7-2.11 and the task metrics against hand-computed values."""
import math

import pytest
import torch

import diffdlo

ROPE = torch.tensor([[[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]]], dtype=torch.float64)
TARGET = torch.tensor([[0.0, 0.0], [0.0, 1.0], [0.0, 2.0]], dtype=torch.float64)


def test_hand_computed_values():
    s2 = math.sqrt(2)
    # eq 2.7: node distances 0, sqrt(2), sqrt(8)
    assert diffdlo.reward_abs_diff(ROPE, TARGET).item() == pytest.approx(-(0 + s2 + 2 * s2))
    # eq 2.10: same pairwise distances (1, 2, 1) -> P = 0
    assert diffdlo.pairwise_shape_term(ROPE, TARGET).item() == pytest.approx(0.0)
    # eq 2.11: rope end-to-end angle atan2(0, -2) = pi, target atan2(-2, 0) = -pi/2: 3pi/2 wraps to pi/2
    assert diffdlo.orientation_error(ROPE, TARGET).item() == pytest.approx(math.pi / 2)
    assert diffdlo.reward_position_orientation(ROPE, TARGET).item() == pytest.approx(-math.pi / 2)
    # shape error: centred rope (-1,0),(0,0),(1,0) vs centred target (0,-1),(0,0),(0,1)
    assert diffdlo.shape_error(ROPE, TARGET).item() == pytest.approx((s2 + 0 + s2) / 3)


def test_pairwise_term_counts_ordered_pairs():
    bent = torch.tensor([[[0.0, 0.0], [1.0, 0.0], [1.0, 1.0]]], dtype=torch.float64)
    # pair (0, 2): sqrt(2) vs 2; counted for (0,2) and (2,0)
    assert diffdlo.pairwise_shape_term(bent, TARGET).item() == pytest.approx(2 * (2 - math.sqrt(2)))


def test_delta_gain_is_positive_when_the_move_helps():
    closer = ROPE * 0.5
    gain = diffdlo.reward_delta_gain(ROPE, closer, TARGET)
    expected = diffdlo.abs_diff(ROPE, TARGET) - diffdlo.abs_diff(closer, TARGET)
    assert gain.item() == pytest.approx(expected.item()) and gain.item() > 0
    assert diffdlo.reward("delta_gain", ROPE, closer, TARGET).item() == pytest.approx(gain.item())


def test_orientation_error_wraps_across_pi():
    a, b = math.pi - 0.05, -math.pi + 0.05                # 0.1 rad apart across the branch cut
    rope = torch.tensor([[[math.cos(a), math.sin(a)], [0.0, 0.0]]], dtype=torch.float64)
    target = torch.tensor([[math.cos(b), math.sin(b)], [0.0, 0.0]], dtype=torch.float64)
    assert diffdlo.orientation_error(rope, target).item() == pytest.approx(0.1)
    reversed_rope = rope.flip(1)
    assert diffdlo.orientation_error(reversed_rope, target).item() == pytest.approx(math.pi - 0.1)


def test_shape_error_is_translation_free_and_orientation_sensitive(params):
    target = diffdlo.target_shape("horizontal", params, dtype=torch.float64)
    moved = (target + torch.tensor([0.4, -0.3], dtype=torch.float64))[None]
    assert diffdlo.shape_error(moved, target).item() == pytest.approx(0.0, abs=1e-12)
    assert bool(diffdlo.is_success(moved, target))
    flipped = target.flip(0)[None]                        # same line, nodes reversed
    assert diffdlo.shape_error(flipped, target).item() > 0.1
    assert not bool(diffdlo.is_success(flipped, target))
    assert bool(diffdlo.is_success(flipped, target, tol=1.0))


def test_rewards_are_batched_and_unknown_names_raise(params):
    pos = diffdlo.random_shape(5, params, torch.Generator().manual_seed(0), dtype=torch.float64)
    target = diffdlo.target_shape("diagonal", params, dtype=torch.float64)
    pegs = torch.tensor([[0.05, 0.02, 0.01], [0.0, 0.0, 0.0]], dtype=torch.float64).expand(5, 2, 3)
    for kind in diffdlo.REWARDS:
        r = diffdlo.reward(kind, pos, pos.flip(0), target, pegs)
        assert r.shape == (5,) and torch.isfinite(r).all()
        for b in range(5):
            single = diffdlo.reward(kind, pos[b:b + 1], pos.flip(0)[b:b + 1], target, pegs[b:b + 1])
            assert single.item() == pytest.approx(r[b].item())
    with pytest.raises(ValueError, match="unknown reward 'nope'"):
        diffdlo.reward("nope", pos, pos, target)
    with pytest.raises(ValueError, match="'route_side_gain' scores the pegs' sides: it needs a route's pegs"):
        diffdlo.reward("route_side_gain", pos, pos, target)


def test_route_side_gain_is_route_gain_plus_five_per_peg_brought_to_its_side(params):
    """A straight route under a peg: the rope moved from over the peg (wrong side) to the route earns the cm of
    error it removed plus 100 x SIDE_COST = 5; the reverse move loses as much."""
    from diffdlo.tasks.routing import SIDE_COST
    n, length = params.n_nodes, params.length
    x = torch.linspace(-length / 2, length / 2, n, dtype=torch.float64)
    route = torch.stack([x, torch.zeros_like(x)], -1)
    pegs = torch.tensor([[[0.0, 0.02, 0.01]]], dtype=torch.float64)
    over = (route + torch.tensor([0.0, 0.045], dtype=torch.float64))[None]
    near = (route + torch.tensor([0.0, -0.01], dtype=torch.float64))[None]
    gain = diffdlo.reward("route_gain", over, near, route)
    side = diffdlo.reward("route_side_gain", over, near, route, pegs)
    assert float(side - gain) == pytest.approx(100 * SIDE_COST, abs=1e-9)
    assert float(diffdlo.reward("route_side_gain", near, over, route, pegs)) == pytest.approx(-float(side))


def test_pairwise_term_has_finite_gradients_at_coincident_nodes():
    x = ROPE.clone().requires_grad_(True)
    diffdlo.pairwise_shape_term(x, TARGET + 0.1).sum().backward()
    assert torch.isfinite(x.grad).all()
