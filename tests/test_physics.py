"""Moves differentiable with respect to the physical parameters (diffdlo.planar.physics): per-rope k_s, k_b, k_d and
mass, checked with gradcheck in float64 against finite differences, and equal to the params' path when they agree."""
import dataclasses

import pytest
import torch

import diffdlo
from diffdlo.planar.physics import PHYSICAL, Physics
from tests.conftest import crumpled


@pytest.fixture(scope="module")
def tiny():
    """4 nodes, a short drag, a fixed settle (threshold 0: every rope runs to the cap, so the substep count does not
    move under the finite differences)."""
    return dataclasses.replace(diffdlo.load_params(), n_nodes=4, length=0.09, max_speed=1.0, settle_max_substeps=12,
                               settle_check_every=4, settle_threshold=0.0)


def test_the_params_numbers_as_physics_give_the_same_move(small):
    sim = diffdlo.Simulator(small, dtype=torch.float64, backend="torch")
    pos = crumpled(3, small, sigma=0.5)
    node, delta = torch.tensor([0, 2, 5]), torch.tensor([[0.02, 0.0], [0.0, -0.03], [0.01, 0.01]], dtype=torch.float64)
    plain = sim.move(pos, node, delta)
    with_physics = sim.move(pos, node, delta, physics=Physics.of(small, 3))
    torch.testing.assert_close(with_physics, plain, rtol=1e-12, atol=1e-15)      # rounding: tensor vs float maths
    kernel = diffdlo.Simulator(small, dtype=torch.float64).move(pos, node, delta)      # the fused path agrees too
    torch.testing.assert_close(with_physics, kernel, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("key", PHYSICAL)
def test_gradcheck_of_free_evolution_in_each_parameter(tiny, key):
    sim = diffdlo.Simulator(tiny, dtype=torch.float64, backend="torch")
    pos = crumpled(2, tiny, sigma=0.8)
    base = Physics.of(tiny, 2)

    def evolve(value):
        physics = dataclasses.replace(base, **{key: value})
        return sim.integrate(pos, None, 15, physics=physics)[0]

    start = getattr(base, key).clone()
    eps = 1e-6 * float(start[0])
    assert torch.autograd.gradcheck(evolve, (start.requires_grad_(True),), eps=eps, atol=1e-7, rtol=1e-4)


@pytest.mark.parametrize("controller", ["kinematic", "pid"])
def test_gradcheck_of_a_whole_move_in_all_parameters(tiny, controller):
    p = dataclasses.replace(tiny, controller=controller, ff_len=0.003)
    sim = diffdlo.Simulator(p, dtype=torch.float64, backend="torch")
    pos = crumpled(2, p, sigma=0.8, seed=3)
    node, delta = torch.tensor([0, 3]), torch.tensor([[0.004, 0.002], [-0.003, 0.004]], dtype=torch.float64)
    scale = torch.tensor([p.k_s, p.k_b, p.k_d, p.mass], dtype=torch.float64)

    def moved(*log_values):                       # log-parametrized, as a calibration fits them
        values = [torch.exp(v) * s for v, s in zip(log_values, scale)]
        return sim.move(pos, node, delta, physics=Physics(*values))

    leaves = tuple(torch.zeros(2, dtype=torch.float64, requires_grad=True) for _ in PHYSICAL)
    assert torch.autograd.gradcheck(moved, leaves, eps=1e-6, atol=1e-8, rtol=1e-4)


def test_each_rope_moves_with_its_own_parameters_only(tiny):
    sim = diffdlo.Simulator(tiny, dtype=torch.float64, backend="torch")
    pos = crumpled(2, tiny, sigma=0.8)
    physics = Physics.of(tiny, 2, requires_grad=True)
    out = sim.move(pos, torch.tensor([0, 1]), torch.tensor([[0.005, 0.0], [0.0, 0.005]], dtype=torch.float64),
                   physics=physics)
    out[0].sum().backward()
    for key in PHYSICAL:
        grad = getattr(physics, key).grad
        assert grad[1] == 0 and grad[0] != 0, key
    stiffer = dataclasses.replace(Physics.of(tiny, 2), k_s=torch.tensor([tiny.k_s, 10 * tiny.k_s], dtype=torch.float64))
    a = sim.integrate(pos, None, 10, physics=stiffer)[0]
    b = sim.integrate(pos, None, 10, physics=Physics.of(tiny, 2))[0]
    assert torch.equal(a[0], b[0]) and not torch.equal(a[1], b[1])


@pytest.mark.parametrize("key,value,message", [
    ("k_s", torch.tensor([1.0, -2.0], dtype=torch.float64), "physics.k_s must be > 0 and finite, got [-2.0]"),
    ("k_d", torch.tensor([0.0, 1.0], dtype=torch.float64), "physics.k_d must be > 0 and finite, got [0.0]"),
    ("mass", float("nan"), "physics.mass must be > 0 and finite, got [nan]"),
    ("k_b", torch.tensor([-1.0, 0.0], dtype=torch.float64), "physics.k_b must be >= 0 and finite, got [-1.0]"),
    ("k_s", torch.ones(3, dtype=torch.float64), "must be a float or a tensor of shape (2,), got shape (3,)"),
    ("k_b", "stiff", "physics.k_b must be a float or a tensor, got 'stiff'"),
])
def test_bad_physics_is_named(tiny, key, value, message):
    sim = diffdlo.Simulator(tiny, dtype=torch.float64, backend="torch")
    pos = crumpled(2, tiny, sigma=0.8)
    with pytest.raises(ValueError) as exc:
        sim.integrate(pos, None, 3, physics=dataclasses.replace(Physics.of(tiny, 2), **{key: value}))
    assert message in str(exc.value)
