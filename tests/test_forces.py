"""Forces are -grad E (autograd), gradcheck-exact, and obey the invariants of an isolated rope."""
import dataclasses
import math

import pytest
import torch

import diffdlo
from conftest import crumpled


def test_forces_equal_minus_energy_gradient_beyond_90_degrees(params, sim64):
    pos = crumpled(8, params)
    # stretch/compress the links too, so the axial term is exercised
    pos = pos * (1 + 0.05 * torch.randn(pos.shape, generator=torch.Generator().manual_seed(1), dtype=pos.dtype))
    assert diffdlo.turning_angles(pos).abs().max() > math.pi / 2, "test shapes must have turns beyond 90 degrees"
    x = pos.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(sim64.energy(x).sum(), x)
    forces = sim64.internal_forces(pos)
    assert forces.abs().max() > 1e-3
    torch.testing.assert_close(forces, -grad, rtol=1e-10, atol=1e-12)


def test_gradcheck_internal_forces(params):
    pos = crumpled(2, params, seed=3)[:, :6].clone().requires_grad_(True)
    f = lambda x: diffdlo.internal_forces(x, params.rest_length, params.k_s, params.k_b)
    assert torch.autograd.gradcheck(f, (pos,), eps=1e-7, atol=1e-5, rtol=1e-4)


def test_straight_rope_at_rest_feels_no_force_and_stays(sim64, params):
    for name in diffdlo.TARGET_NAMES:
        pos = diffdlo.target_shape(name, params, dtype=torch.float64)[None]
        assert sim64.internal_forces(pos).abs().max() < 1e-12
        new, vel = sim64.integrate(pos, None, 200)
        assert (new - pos).abs().max() < 1e-12 and vel.abs().max() < 1e-12


def test_translation_and_rotation_invariance(sim64, params):
    pos = crumpled(3, params, seed=4)
    forces = sim64.internal_forces(pos)
    shift = torch.tensor([0.3, -0.7], dtype=pos.dtype)
    torch.testing.assert_close(sim64.internal_forces(pos + shift), forces, rtol=1e-9, atol=1e-11)
    a = 0.83
    rot = torch.tensor([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]], dtype=pos.dtype)
    torch.testing.assert_close(sim64.internal_forces(pos @ rot.T), forces @ rot.T, rtol=1e-9, atol=1e-11)


def test_move_commutes_with_translation_and_rotation(sim64, params):
    pos = crumpled(2, params, sigma=0.3, seed=5)
    node = torch.tensor([3, 17])
    delta = torch.tensor([[0.04, -0.03], [-0.02, 0.05]], dtype=torch.float64)
    base = sim64.move(pos, node, delta)
    shift = torch.tensor([0.2, 0.1], dtype=torch.float64)
    torch.testing.assert_close(sim64.move(pos + shift, node, delta), base + shift, rtol=0, atol=1e-9)
    a = -1.1
    rot = torch.tensor([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]], dtype=torch.float64)
    torch.testing.assert_close(sim64.move(pos @ rot.T, node, delta @ rot.T), base @ rot.T, rtol=0, atol=1e-9)


def test_momentum_conserved_without_damping(params):
    p = dataclasses.replace(params, k_d=0.0)
    sim = diffdlo.Simulator(p, dtype=torch.float64)
    pos = crumpled(2, params, seed=6)
    vel = 0.05 * torch.randn(pos.shape, generator=torch.Generator().manual_seed(7), dtype=pos.dtype)
    m = p.node_mass

    def momenta(x, v):
        linear = m * v.sum(1)
        angular = m * (x[..., 0] * v[..., 1] - x[..., 1] * v[..., 0]).sum(1)
        return linear, angular

    lin0, ang0 = momenta(pos, vel)
    new, new_vel = sim.integrate(pos, vel, 300)
    lin1, _ = momenta(new, new_vel)
    torch.testing.assert_close(lin1, lin0, rtol=0, atol=1e-13)
    assert (new - pos).abs().max() > 1e-3, "the rope must actually move"
    # Semi-implicit Euler conserves angular momentum of central-pair-free forces only to O(dt); check it drifts
    # by much less than its size over the run (a sign error in the bending force breaks this by orders).
    x_half = new - 0.5 * p.dt * new_vel
    ang1 = m * (x_half[..., 0] * new_vel[..., 1] - x_half[..., 1] * new_vel[..., 0]).sum(1)
    assert ((ang1 - ang0).abs() < 0.02 * ang0.abs().clamp_min(1e-6)).all()


def test_damped_free_evolution_loses_energy(sim64, params):
    pos = crumpled(2, params, seed=8) * 1.02       # stretched: stored axial energy
    vel = torch.zeros_like(pos)
    e_prev = sim64.energy(pos)
    for _ in range(5):
        pos, vel = sim64.integrate(pos, vel, 40)
        e = sim64.energy(pos) + 0.5 * params.node_mass * (vel ** 2).sum((1, 2))
        assert (e < e_prev).all()
        e_prev = e
