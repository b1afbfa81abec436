"""Pegs and the second gripper (diffdlo/planar/contact.py, Simulator.move(..., pegs, pin)): the contact forces are -grad
of the contact energy, a move in contact is gradcheck-exact, no rope ends inside a peg, a rope dragged around a peg
wraps and stays wrapped, a node released above a peg is pushed out along the peg's radius, momentum holds with
contact off and energy is only lost to damping, and every bad input is refused naming the value."""
import dataclasses
import math

import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import diffdlo
from benchmarks.contact_checks import line, path_scenes, winding, wrapped
from diffdlo.planar import contact, simulator
from diffdlo.planar.contact import PegError
from diffdlo.planar.params import ParamsError

F64 = torch.float64


# ------------------------------------------------------------------ the contact model
def contact_states(params):
    """Ropes touching pegs every way: a link's middle (t inside), a node (t clamped), in the smooth ramp (z < w) and
    past it, with two pegs per rope (B, K, 3)."""
    r, w = params.rope_radius, params.contact_width
    base = line(params).repeat(4, 1, 1)
    mid = float(base[0, 3:5, 0].mean())                           # between nodes 3 and 4
    node = float(base[0, 10, 0])
    pegs = torch.tensor([[[mid, 0.01 + r - 0.3 * w, 0.01], [node, -(0.008 + r - 0.5 * w), 0.008]],
                         [[mid, 0.01 + r - 3.0 * w, 0.01], [node, -(0.008 + r - 2.0 * w), 0.008]],
                         [[0.0, 0.3, 0.01], [node + 0.004, -(0.004 + r - 0.7 * w), 0.004]],
                         [[mid, -(0.012 + r - 1.5 * w), 0.012], [-0.2, 0.02 + r - 0.2 * w, 0.02]]], dtype=F64)
    wiggle = 0.002 * torch.randn(base.shape, generator=torch.Generator().manual_seed(0), dtype=F64)
    return base + wiggle, pegs


def test_contact_forces_are_minus_the_energy_gradient(params):
    pos, pegs = contact_states(params)
    z = contact.overlap(pos, pegs, params.rope_radius)
    w = params.contact_width
    assert bool(((z > 0) & (z < w)).any()) and bool((z > w).any()), "states must cover the ramp and the spring"
    weight = torch.ones(pos.shape[0], pos.shape[1] - 1, dtype=F64)
    weight[0, 3] = 0.0                                                # a lifted link feels nothing
    args = (params.rope_radius, params.contact_stiffness, params.contact_width)
    x = pos.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(contact.energy(x, pegs, *args, weight).sum(), x)
    forces = contact.forces(pos, pegs, *args, weight)
    assert forces.abs().max() > 1.0
    torch.testing.assert_close(forces, -grad, rtol=1e-10, atol=1e-10)
    # the lifted link's nodes get nothing from it: only node 10's peg pushes rope 0 besides links 3-4
    free = contact.forces(pos, pegs, *args)
    assert float((free[0, 3:5] - forces[0, 3:5]).abs().max()) > 1.0


def test_contact_forces_carry_no_torque_about_the_peg_and_vanish_clear_of_it(params):
    pos, pegs = contact_states(params)
    one = pegs[:, :1]
    f = contact.forces(pos, one, params.rope_radius, params.contact_stiffness, params.contact_width)
    rel = pos - one[:, :, :2]
    torque = (rel[..., 0] * f[..., 1] - rel[..., 1] * f[..., 0]).sum(-1)  # a push along the peg's radius
    assert float(torque.abs().max()) < 1e-9 * float(f.abs().max())
    far = torch.tensor([[0.0, 0.5, 0.01]], dtype=F64).expand(4, 1, 3)
    assert float(contact.forces(pos, far, params.rope_radius, 1e4, 1e-3).abs().max()) == 0.0


def test_the_penalty_is_twice_continuously_differentiable():
    w = 0.002
    for z0 in (0.0, w):
        below, above = contact.penalty(torch.tensor([z0 - 1e-12], dtype=F64), w), \
            contact.penalty(torch.tensor([z0 + 1e-12], dtype=F64), w)
        for lo, hi in zip(below, above):
            assert abs(float(lo - hi)) < 1e-9
    z = torch.linspace(-w, 3 * w, 401, dtype=F64, requires_grad=True)
    h, h1, h2 = contact.penalty(z, w)
    (g1,) = torch.autograd.grad(h.sum(), z, create_graph=True)
    (g2,) = torch.autograd.grad(g1.sum(), z)
    torch.testing.assert_close(g1, h1, rtol=0, atol=1e-15)
    torch.testing.assert_close(g2, h2, rtol=0, atol=1e-12)


def test_gradcheck_contact_forces(params):
    pos, pegs = contact_states(params)
    x = pos[:2, :7].clone().requires_grad_(True)
    f = lambda p: contact.forces(p, pegs[:2], params.rope_radius, params.contact_stiffness, params.contact_width)
    assert float(contact.depth(pos[:2, :7], pegs[:2], params.rope_radius).min()) > 0
    assert torch.autograd.gradcheck(f, (x,), eps=1e-7, atol=1e-4, rtol=1e-5)


# ------------------------------------------------------------------ moves in contact
@pytest.fixture(scope="module")
def small_contact(small):
    """6 nodes, 0.15 m, drags at 1 m/s: a move is ~40 substeps."""
    return small


def hooked(params):
    """A short rope with a peg just above its node 4 and a drag of its end node that pulls the rope into it."""
    pos = line(params)
    pegs = torch.tensor([[float(pos[0, 4, 0]), 0.006 + params.rope_radius + 0.0005, 0.006]], dtype=F64)
    return pos, pegs, torch.tensor([5]), torch.tensor([[0.0, 0.0305]], dtype=F64)   # 30.5 substeps: a release share


def test_gradcheck_through_a_move_in_contact_with_a_pin(small_contact):
    sim = diffdlo.Simulator(small_contact, dtype=F64, backend="torch")
    pos, pegs, node, delta = hooked(small_contact)
    _, info = sim.move(pos, node, delta, pegs, return_info=True, record_every=1)
    assert float(contact.depth(info.frames[:, 0], pegs.expand(len(info.frames), 1, 3),
                               small_contact.rope_radius).max()) > small_contact.contact_width, "no contact"
    pin = torch.tensor([0])

    def f(p, d):
        return sim.move(p, node, d, pegs, pin)

    x, d = pos.clone().requires_grad_(True), delta.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(f, (x, d), eps=1e-7, atol=1e-5, rtol=1e-4)


def test_pegs_far_away_and_no_pins_leave_a_move_unchanged_bit_for_bit(params):
    for backend in ("torch", "auto"):
        sim = diffdlo.Simulator(params, dtype=torch.float32, backend=backend)
        pos = sim.random_shape(3, torch.Generator().manual_seed(2))
        node, delta = torch.tensor([0, 7, 19]), torch.tensor([[0.05, 0.02], [-0.03, 0.04], [0.0, -0.1]])
        base = sim.move(pos, node, delta)
        far = torch.tensor([[5.0, 5.0, 0.01], [-5.0, 5.0, 0.02]])
        if sim.contact_engine == sim.engine:                    # the same engine runs the move with pegs
            assert torch.equal(sim.move(pos, node, delta, far), base)
        assert torch.equal(sim.move(pos, node, delta, pin=torch.tensor([-1, -1, -1])), base)
        assert torch.equal(sim.move(pos, node, delta, None, None), base)


def test_a_pin_holds_its_node_until_the_release(params):
    sim = diffdlo.Simulator(params, dtype=F64)
    pos = line(params)
    node, delta = torch.tensor([19]), torch.tensor([[0.0, 0.1]], dtype=F64)
    free = sim.move(pos, node, delta)
    held, info = sim.move(pos, node, delta, pin=torch.tensor([17]), return_info=True, record_every=10)
    drag = int(info.drag_substeps[0])
    during, after = info.frames[: drag // 10 + 1, 0, 17], info.frames[drag // 10 + 1:, 0, 17]
    torch.testing.assert_close(during, pos[0, 17].expand_as(during), rtol=0, atol=0)
    assert float((after[-1] - pos[0, 17]).norm()) > 1e-3                # released with the grasp, it follows
    assert float((held - free).abs().max()) > 0.005                    # the pin changed the move


def backends_with_contact(params):
    """The engines that run moves with pegs here: the eager path always, the C++ kernel where it builds."""
    return [b for b in ("torch", "kernel")
            if b == "torch" or diffdlo.Simulator(params, dtype=F64).contact_engine == "kernel"]


@pytest.mark.parametrize("backend", ["torch", "kernel"])
@pytest.mark.parametrize("whole", [True, False])
def test_a_pin_is_released_on_the_drags_last_substep_not_one_later(params, backend, whole):
    """Every substep recorded: the pinned node sits exactly where it lay up to the release, and moves on the
    substep after it. A drag of a whole number of substeps (whole) holds the pin through its last substep; one
    ending within its last substep releases the pin there by the same share phi as the grasped node."""
    if backend not in backends_with_contact(params):
        pytest.skip("the C++ kernel is unavailable")
    sim = diffdlo.Simulator(params, dtype=F64, backend=backend)
    pos = line(params)
    step = params.max_speed * params.dt
    length = 40 * step if whole else 40.4 * step
    node, delta, pin = torch.tensor([19]), torch.tensor([[0.0, length]], dtype=F64), torch.tensor([15])
    _, info = sim.move(pos, node, delta, pin=pin, return_info=True, record_every=1)
    path = int(info.drag_substeps[0])
    assert path == (40 if whole else 41)
    at_pin = info.frames[:, 0, 15]
    held = path if whole else path - 1                          # the last substep the pin is exactly held
    torch.testing.assert_close(at_pin[:held + 1], pos[0, 15].expand(held + 1, 2), rtol=0, atol=0)
    after = (at_pin[held + 1:] - pos[0, 15]).norm(dim=-1)     # released: it follows the rope from here on
    assert bool((after > 0).all()) and bool((at_pin[held + 2:held + 10] != at_pin[held + 1:held + 9]).any(-1).all())


@pytest.mark.parametrize("backend", ["torch", "kernel"])
def test_the_contact_sets_in_at_the_peg_radius_plus_the_rope_radius(params, backend):
    """A straight rope at rest beside a peg: its axis 0.1 mm farther than R + r from the peg's centre, a settle
    with the peg is the settle without it bit for bit; 1 mm nearer, the rope is pushed away from the peg."""
    if backend not in backends_with_contact(params):
        pytest.skip("the C++ kernel is unavailable")
    sim = diffdlo.Simulator(params, dtype=F64, backend=backend)
    pos = line(params)
    radius = 0.01
    reach = radius + params.rope_radius
    free = sim.settle(pos)
    outside = torch.tensor([[float(pos[0, 10, 0]), reach + 1e-4, radius]], dtype=F64)
    assert torch.equal(sim.settle(pos, pegs=outside), free)
    inside = torch.tensor([[float(pos[0, 10, 0]), reach - 1e-3, radius]], dtype=F64)
    pushed = sim.settle(pos, pegs=inside)
    assert float(pushed[0, 10, 1] - free[0, 10, 1]) < -1e-4    # pushed down, away from the peg above it


@pytest.mark.parametrize("backend", ["torch", "kernel"])
def test_a_padded_board_is_its_pegs_and_a_radius_0_row_is_no_peg(params, backend):
    """The one board convention: rows of zeros (radius 0; one at the origin, under the rope) are empty slots. A move
    on the padded board equals the move on its pegs bit for bit, and the contact functions see no peg in them."""
    if backend not in backends_with_contact(params):
        pytest.skip("the C++ kernel is unavailable")
    sim = diffdlo.Simulator(params, dtype=F64, backend=backend)
    pos = line(params).repeat(2, 1, 1)
    pegs = torch.tensor([[0.05, 0.0155, 0.01]], dtype=F64)
    padded = torch.cat([pegs, torch.zeros(2, 3, dtype=F64)])
    node, delta = torch.tensor([3, 12]), torch.tensor([[0.0, 0.05], [0.03, 0.02]], dtype=F64)
    assert torch.equal(sim.move(pos, node, delta, padded), sim.move(pos, node, delta, pegs))
    zero = torch.zeros(2, 2, 3, dtype=F64)
    assert torch.equal(contact.forces(pos, zero, params.rope_radius, 1e4, 1e-3), torch.zeros_like(pos))
    assert float(contact.energy(pos, zero, params.rope_radius, 1e4, 1e-3).abs().max()) == 0
    assert bool((contact.depth(pos, zero, params.rope_radius) == -math.inf).all())


def test_a_rope_dragged_around_a_peg_wraps_and_stays_wrapped(params):
    sim = diffdlo.Simulator(params, dtype=F64)
    pos, pegs, frames = wrapped(params, sim, record_every=5)
    frames = torch.cat(frames)
    deepest = float(contact.depth(frames, pegs.expand(len(frames), 1, 3), params.rope_radius).max())
    turn = float(winding(pos, pegs[0, :2]))
    assert turn > 1.8 * math.pi, turn
    assert 0 < deepest < params.rope_radius                        # it touched, and never deeper than r
    # pinned at one end, the other dragged away: the loop is pulled tight round the peg, not through it
    pos, info = sim.move(pos, torch.tensor([19]), torch.tensor([[-0.1, 0.0]], dtype=F64), pegs,
                         torch.tensor([0]), return_info=True, record_every=5)
    frames = info.frames[:, 0]
    assert float(contact.depth(frames, pegs.expand(len(frames), 1, 3), params.rope_radius).max()) < params.rope_radius
    assert float(winding(pos, pegs[0, :2])) > 1.8 * math.pi
    # released, it rests against the peg: 2 s of free evolution keep it wrapped and touching
    rest, _ = sim.integrate(pos, None, 2000, pegs=pegs)
    assert float(winding(rest, pegs[0, :2])) > 1.8 * math.pi
    assert float(contact.depth(rest, pegs[None], params.rope_radius)) > 0


def test_a_node_released_above_a_peg_is_pushed_out_along_the_peg_radius(params):
    """The grasped node is lifted over pegs during the drag; released above one, the penalty pushes it out the
    shortest way, along the peg's radius through the release point, and the rope ends outside the peg."""
    sim = diffdlo.Simulator(params, dtype=F64)
    pos = line(params)
    release = pos[0, 19] + torch.tensor([0.05, 0.0], dtype=F64)
    centre = release + torch.tensor([0.01, 0.006], dtype=F64)
    pegs = torch.cat([centre, torch.tensor([0.02], dtype=F64)])[None]
    assert float((release - centre).norm()) < 0.02                     # released with its axis inside the peg
    out, info = sim.move(pos, torch.tensor([19]), torch.tensor([[0.05, 0.0]], dtype=F64), pegs, return_info=True,
                         record_every=1)
    drag = int(info.drag_substeps[0])
    torch.testing.assert_close(info.frames[drag, 0, 19], release, rtol=0, atol=1e-12)   # carried over the peg
    assert float(contact.depth(out, pegs[None], params.rope_radius)) < params.contact_width
    away, pushed = release - centre, out[0, 19] - centre
    cos = float((away @ pushed) / (away.norm() * pushed.norm()))
    assert cos > math.cos(math.radians(20)), math.degrees(math.acos(cos))


# ------------------------------------------------------------------ no rope ends inside a peg
SMALL = dataclasses.replace(diffdlo.load_params("cable"), n_nodes=6, length=0.15, settle_max_substeps=100,
                            settle_check_every=50)
SIM = diffdlo.Simulator(SMALL, dtype=F64)


@settings(derandomize=True, database=None, deadline=None, max_examples=30,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much])
@given(st.lists(st.floats(-1.2, 1.2), min_size=5, max_size=5), st.integers(1, 4),
       st.lists(st.tuples(st.floats(-0.08, 0.08), st.floats(-0.08, 0.08), st.floats(0.002, 0.03)),
                min_size=4, max_size=4),
       st.integers(0, 5), st.floats(0, 2 * math.pi), st.booleans(), st.integers(-1, 5))
def test_no_move_ends_with_the_rope_inside_a_peg(turns, k, pegs, node, angle, largest, pin):
    """Random 6-node ropes, 1-4 pegs of 2-30 mm, drags up to the largest (0.1 m at 0.1 m/s), with and without a pin:
    every move ends with every link's overlap under the rope's radius (its axis outside every peg)."""
    heading = torch.cumsum(torch.tensor(turns, dtype=F64), 0)
    steps = SMALL.rest_length * torch.stack([heading.cos(), heading.sin()], -1)
    pos = torch.cat([torch.zeros(1, 2, dtype=F64), steps.cumsum(0)])[None]
    pos = pos - pos.mean(1, keepdim=True)
    pegs = torch.tensor(pegs[:k], dtype=F64)
    if float(contact.depth(pos, pegs[None], SMALL.rope_radius)) > SMALL.rope_radius:
        return                                                       # not an admissible start (refused, tested below)
    gaps = (pegs[:, None, :2] - pegs[None, :, :2]).norm(dim=-1) - pegs[:, None, 2] - pegs[None, :, 2]
    if bool((gaps + 9 * torch.eye(k, dtype=F64) < 2 * SMALL.rope_radius).any()):
        return                                                       # not a board (refused, tested below)
    length = 0.1 if largest else 0.04
    delta = length * torch.tensor([[math.cos(angle), math.sin(angle)]], dtype=F64)
    pin_t = torch.tensor([pin if pin != node else -1])
    out = SIM.move(pos, torch.tensor([node]), delta, pegs, pin_t)
    assert torch.isfinite(out).all()
    assert float(contact.depth(out, pegs[None], SMALL.rope_radius)) <= SMALL.rope_radius
    SIM.move(out, torch.tensor([node]), -delta, pegs, pin_t)         # the result is a valid start


CLEARANCE = simulator.PUSH_OUT_CLEARANCE_RADII * diffdlo.load_params("cable").rope_radius


@settings(derandomize=True, database=None, deadline=None, max_examples=12,
          suppress_health_check=[HealthCheck.too_slow])
@given(st.integers(0, 2 ** 16), st.sampled_from([(0.002, 0.004), (0.002, 0.008), (0.004, 0.008)]), st.booleans())
def test_a_rope_carried_over_a_peg_is_always_put_down_outside_it(seed, small, pins):
    """The defect of issue 68 where it bites: 512 ropes an example (6,144 moves), a small peg on the grasped node's
    path so that the lifted links are put down across it, 0-3 pegs beside the path, every two the rope's diameter
    apart. Every move ends with every axis outside every peg, and the next move accepts the result. Some moves of
    the sweep are left by the settle inside a peg (the defect; counted by benchmarks.contact_checks's put_down and
    shown by the next test), so this property could fail."""
    p = diffdlo.load_params("cable")
    sim = diffdlo.Simulator(p, dtype=F64)
    pos, pegs, node, delta, pin = path_scenes(p, 512, seed, small=small, pins=pins)
    out, info = sim.move(pos, node, delta, pegs, pin, return_info=True)
    assert float(contact.depth(out, pegs, p.rope_radius).max()) <= p.rope_radius - 0.99 * CLEARANCE
    assert bool((info.drag_share[~info.pushed_out] <= 1).all())
    sim.move(out, node, -0.5 * delta, pegs, pin)                      # raises if a result is no valid start


# seed and rope of path_scenes(p, 512, seed) whose settle ends inside a peg: pushed out; let go at half its drag
PUT_DOWN_CASES = {"pushed out": (0, 63, 1.0), "let go earlier": (1, 41, 0.5)}


@pytest.mark.parametrize("case", list(PUT_DOWN_CASES))
def test_a_rope_the_settle_leaves_inside_a_peg_is_put_down_outside_it_on_every_engine(params, case):
    """The settle alone leaves these two ropes with an axis inside a peg, a start the next move refuses (the
    defect); the move pushes one out, and lets go of the other at half its drag, on the eager path and in the
    kernel alike, and the result is a valid start."""
    seed, b, share = PUT_DOWN_CASES[case]
    pos, pegs, node, delta, pin = (x[b:b + 1] for x in path_scenes(params, 512, seed))
    results = {}
    for backend in ("torch", "kernel"):
        sim = diffdlo.Simulator(params, dtype=F64, backend=backend)
        if backend == "kernel" and sim.contact_engine != "kernel":
            continue
        settled, _ = sim._run_move(pos, torch.zeros_like(pos), node, delta, sim._check_pegs(pos, pegs), pin, None, 0,
                                   False, False)
        assert float(contact.depth(settled, pegs, params.rope_radius)) > params.rope_radius     # the defect
        with pytest.raises(ValueError, match="deep in peg"):
            sim.move(settled, node, -delta, pegs, pin)
        out, info = sim.move(pos, node, delta, pegs, pin, return_info=True, record_every=50)
        assert float(info.drag_share[0]) == share and bool(info.pushed_out[0]) == (share == 1.0)
        assert float(contact.depth(out, pegs, params.rope_radius)) <= params.rope_radius - 0.99 * CLEARANCE
        torch.testing.assert_close(info.frames[-1], out, rtol=0, atol=0)
        sim.move(out, node, -delta, pegs, pin)
        results[backend] = out
    if "kernel" in results:
        torch.testing.assert_close(results["kernel"], results["torch"], rtol=0, atol=1e-9)


def test_gradcheck_through_a_move_pushed_out_of_a_peg(params):
    """The push-out is differentiable: gradcheck (float64) of the final rope w.r.t. the drag through a move that
    the settle leaves inside a peg, on the kernel's adjoint (and the eager path where the kernel is absent)."""
    seed, b, _ = PUT_DOWN_CASES["pushed out"]
    pos, pegs, node, delta, pin = (x[b:b + 1] for x in path_scenes(params, 512, seed))
    sim = diffdlo.Simulator(params, dtype=F64)
    _, info = sim.move(pos, node, delta, pegs, pin, return_info=True)
    assert bool(info.pushed_out[0])
    weights = torch.randn(pos.shape, generator=torch.Generator().manual_seed(0), dtype=F64)
    f = lambda d: (sim.move(pos, node, d, pegs, pin) * weights).sum()
    assert torch.autograd.gradcheck(f, (delta.clone().requires_grad_(),), eps=1e-7, atol=1e-5, rtol=1e-4)


# ------------------------------------------------------------------ momentum and energy
def test_momentum_is_conserved_with_contact_off_and_not_with_it_on(params):
    p = dataclasses.replace(params, k_d=0.0, dt=2.5e-4)
    sim = diffdlo.Simulator(p, dtype=F64, backend="torch")
    pos = line(p)
    vel = torch.zeros_like(pos)
    vel[0, :, 1] = 0.5                                                  # the rope flies at +y into a peg
    vel[0, 5, 0] = 0.3
    clear = torch.tensor([[0.0, 0.5, 0.01]], dtype=F64)
    hit = torch.tensor([[0.0, 0.03, 0.01]], dtype=F64)
    momentum = lambda v: float(v[0].sum(0).norm()) * p.node_mass
    _, v_clear = sim.integrate(pos, vel, 200, pegs=clear)
    _, v_hit = sim.integrate(pos, vel, 200, pegs=hit)
    assert abs(momentum(v_clear) - momentum(vel)) < 1e-12
    assert momentum(vel) - momentum(v_hit) > 0.1 * momentum(vel)


def total_energy(sim, pos, vel, pegs):
    p = sim.params
    return float(0.5 * p.node_mass * (vel ** 2).sum() + sim.energy(pos).sum() + sim.contact_energy(pos, pegs).sum())


def test_energy_is_kept_without_damping_and_only_lost_with_it(params):
    """A rope thrown at a peg: with k_d = 0 its energy (kinetic + elastic + contact) stays within 1 % through the
    bounce (symplectic Euler keeps it close, it never grows); with damping it only falls."""
    for k_d in (0.0, 0.05):
        p = dataclasses.replace(params, k_d=k_d, dt=2.5e-4)
        sim = diffdlo.Simulator(p, dtype=F64, backend="torch")
        pos, vel = line(p), torch.zeros(1, p.n_nodes, 2, dtype=F64)
        vel[0, :, 1] = 0.5
        pegs = torch.tensor([[0.02, 0.03, 0.01]], dtype=F64)
        energies, touching = [total_energy(sim, pos, vel, pegs)], 0.0
        for _ in range(40):
            pos, vel = sim.integrate(pos, vel, 10, pegs=pegs)
            energies.append(total_energy(sim, pos, vel, pegs))
            touching = max(touching, float(sim.contact_energy(pos, pegs).sum()))
        assert touching > 0.02 * energies[0], "the rope must bounce off the peg"
        if k_d == 0.0:
            assert max(abs(e - energies[0]) for e in energies) < 0.01 * energies[0]
        else:
            assert all(b <= a + 1e-4 * energies[0] for a, b in zip(energies, energies[1:]))
            assert energies[-1] < 0.9 * energies[0]


# ------------------------------------------------------------------ bad input
@pytest.mark.parametrize("pegs, match", [
    (torch.tensor([0.0, 0.1, 0.01]), r"shape \(K, 3\) or \(1, K, 3\).*got \(3,\)"),
    (torch.tensor([[0.0, 0.1]]), r"got \(1, 2\)$"),
    (torch.zeros(2, 1, 3), r"got \(2, 1, 3\)"),
    (torch.tensor([[0.0, 0.1, -0.01]]), r"radius must be >= 0 m \(0: an empty slot, no peg\), got \[-0.01"),
    (torch.tensor([[0.0, 0.1, 0.01], [0.0, 0.125, 0.01]]),
     r"pegs 0 \[0.0, 0.1, 0.01\] and 1 \[0.0, 0.125, 0.01\] \(rope 0\) leave a gap of 5 mm between them, less "
     r"than the rope's diameter \(10 mm\)"),
    (torch.tensor([[float("nan"), 0.1, 0.01]]), r"finite.*nan"),
    (torch.tensor([[0.0, float("inf"), 0.01]]), r"finite.*inf"),
    ([[0.0, 0.1, 0.01]], r"must be a tensor.*got list"),
    (torch.tensor([[0, 1, 1]]), r"floating-point.*torch.int64"),
])
def test_bad_pegs_are_refused_naming_the_value(params, pegs, match):
    sim = diffdlo.Simulator(params, dtype=torch.float32)
    pos = line(params).float()
    with pytest.raises(PegError, match=match):
        sim.move(pos, torch.tensor([0]), torch.zeros(1, 2), pegs)
    with pytest.raises(PegError, match=match):
        sim.integrate(pos, None, 10, pegs=pegs)


def test_a_start_shape_inside_a_peg_is_refused(params):
    sim = diffdlo.Simulator(params, dtype=F64)
    pos = line(params).repeat(2, 1, 1)
    pegs = torch.tensor([[[0.3, 0.3, 0.01]], [[0.1, 0.008, 0.01]]], dtype=F64)    # rope 1's axis 2 mm in its peg
    with pytest.raises(ValueError, match=r"rope 1's link \d+-\d+ lies 7 mm deep in peg 0 \[0.1, 0.008, 0.01\]"):
        sim.move(pos, torch.tensor([0, 0]), torch.zeros(2, 2, dtype=F64), pegs)
    sim.move(pos, torch.tensor([0, 0]), torch.zeros(2, 2, dtype=F64),        # touching (axis outside) is fine
             torch.tensor([[[0.3, 0.3, 0.01]], [[0.1, 0.0155, 0.01]]], dtype=F64))


@pytest.mark.parametrize("pin, match", [
    (torch.tensor([3, 5]), r"pin must differ from the grasped node: ropes \[1\] pin node \[5\]"),
    (torch.tensor([3, 20]), r"pin node ids must be in \[0, 19\] or -1 for no pin, got \[20\]"),
    (torch.tensor([-2, 0]), r"got \[-2\]"),
    (torch.tensor([3]), r"pin must have shape \(2,\)"),
    (torch.tensor([3.0, 1.0]), r"pin must be an integer tensor"),
])
def test_bad_pins_are_refused_naming_the_value(params, pin, match):
    sim = diffdlo.Simulator(params, dtype=F64)
    with pytest.raises((ValueError, TypeError), match=match):
        sim.move(line(params).repeat(2, 1, 1), torch.tensor([0, 5]), torch.zeros(2, 2, dtype=F64), pin=pin)


def test_a_contact_stiffness_beyond_the_stability_margin_is_refused(params):
    stiff = dataclasses.replace(params, contact_stiffness=2e5)
    sim = diffdlo.Simulator(stiff, dtype=F64)
    with pytest.raises(ParamsError, match=r"'contact_stiffness' = 200000.0 N/m makes the integrator unstable"):
        sim.move(line(params), torch.tensor([0]), torch.zeros(1, 2, dtype=F64), torch.tensor([[0.0, 0.3, 0.01]]))
    sim.move(line(params), torch.tensor([0]), torch.zeros(1, 2, dtype=F64))     # without pegs it is no concern
    with pytest.raises(ParamsError, match=r"'contact_width' must be > 0, got -0.001"):
        dataclasses.replace(params, contact_width=-0.001)
    with pytest.raises(ParamsError, match=r"'rope_radius' must be > 0, got 0"):
        dataclasses.replace(params, rope_radius=0)


def test_the_checks_command_refuses_bad_flags_and_an_existing_file(tmp_path, capsys):
    from benchmarks import contact_checks
    (tmp_path / "results.json").write_text("{}")
    assert contact_checks.main(["--out", str(tmp_path)]) == 2
    assert (tmp_path / "results.json").read_text() == "{}"
    figure = tmp_path / "wrap.png"
    figure.write_text("mine")
    assert contact_checks.main(["--figure", str(figure)]) == 2
    assert figure.read_text() == "mine" and "--overwrite" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        contact_checks.main(["--scenes", "0"])
    assert "--scenes must be >= 1, got 0" in capsys.readouterr().err


def test_the_kernels_start_check_equals_the_torch_overlap(params):
    from diffdlo.planar.backends import kernel
    if not kernel.available():
        pytest.skip(f"no C++ kernel: {kernel.unavailable_reason()}")
    pos, pegs = contact_states(params)
    for dtype in (torch.float64, torch.float32):
        fast = kernel.deepest_overlap(pos.to(dtype), pegs.to(dtype), params.rope_radius)
        torch.testing.assert_close(fast, contact.depth(pos.to(dtype), pegs.to(dtype), params.rope_radius),
                                   rtol=0, atol=1e-12 if dtype == torch.float64 else 1e-6)
    assert float(fast.max()) > 0
