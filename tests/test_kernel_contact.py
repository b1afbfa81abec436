"""The fused C++ kernel with pegs (diffdlo/planar/contact.py) and the pin, against the eager torch path (the oracle):
the Hessian-vector product of the contact energy, positions, run statistics, frames and the gradients w.r.t. pos, vel,
delta and the per-rope physics, on the vectorized lane groups and the per-rope path alike; gradcheck; float32; and
without pegs and pin the very code it ran before."""
import dataclasses

import pytest
import torch

import diffdlo
from diffdlo.planar import contact
from diffdlo.planar.backends import kernel
from diffdlo.planar.physics import PHYSICAL, Physics
from tests.conftest import crumpled

pytestmark = pytest.mark.skipif(not kernel.available(), reason=f"kernel unavailable: {kernel.unavailable_reason()}")

LANES = kernel.lanes() if kernel.available() else 16
# Two full vectorized lane groups and five ropes on the per-rope path.
BATCH = 2 * LANES + 5


@pytest.fixture(autouse=True)
def _one_thread(one_thread):
    """Both paths on one torch thread (the kernel's own threads follow torch's count)."""


def short(p, **changes):
    """Fewer substeps, same phases (as tests/test_kernel.py): drags at 0.3 m/s, the settle checked every 50
    substeps up to 300, its 0.02 m/s threshold stopping some ropes early and others at the cap."""
    return dataclasses.replace(p, **{"max_speed": 0.3, "settle_threshold": 0.02, "settle_check_every": 50,
                                     "settle_max_substeps": 300, **changes})


@pytest.fixture(scope="module")
def rope8(params):
    """8 nodes, 0.2 m: the gradients' rope."""
    return short(params, n_nodes=8, length=0.2, settle_max_substeps=200)


def place(pos, p, b, pegs, slot, centre, radius):
    """Put peg ``slot`` of rope b at centre (x, y) with ``radius`` if the start state allows it (its axis clear of
    every peg, an overlap of at most 0.9 rope radii) and the board does (the rope's diameter between any two pegs);
    returns whether it did."""
    trial = pegs[b].clone()
    trial[slot] = torch.tensor([float(centre[0]), float(centre[1]), radius], dtype=pegs.dtype)
    if float(contact.overlap(pos[b:b + 1], trial[None, :slot + 1], p.rope_radius).max()) > 0.9 * p.rope_radius:
        return False
    gaps = (trial[:slot, :2] - trial[slot, :2]).norm(dim=-1) - trial[:slot, 2] - radius
    if bool((gaps < 2 * p.rope_radius).any()):
        return False
    pegs[b] = trial
    return True


def scene(p, batch=BATCH, seed=0, k_max=4, drag=0.06, special=True):
    """Ropes, actions and per-rope pegs (B, k_max, 3): rope b gets 1 + b % k_max pegs that already touch a link
    (overlap 0.1 - 0.9 rope radii), the first on the grasped node's path where one fits (its lifted links pass
    over it), the unused slots far away; pins on two ropes in three (-1 on the others). With ``special``, rope 0
    and the first per-rope one only settle, ropes 1 and the second per-rope one drag farther than max_disp."""
    pos = crumpled(batch, p, sigma=0.3, seed=seed)
    g = torch.Generator().manual_seed(seed + 100)
    node = torch.randint(0, p.n_nodes, (batch,), generator=g)
    delta = (torch.rand(batch, 2, generator=g, dtype=torch.float64) * 2 - 1) * drag
    if special:
        first = batch - batch % LANES if batch % LANES else 0
        delta[0] = delta[first] = 0.0
        delta[1] = torch.tensor([0.3, -0.2], dtype=torch.float64)
        delta[min(first + 1, batch - 1)] = torch.tensor([-0.2, 0.25], dtype=torch.float64)
    pin = torch.randint(0, p.n_nodes, (batch,), generator=g)
    pin = torch.where(pin == node, (pin + 1) % p.n_nodes, pin)
    pin[::3] = -1
    pegs = torch.zeros(batch, k_max, 3, dtype=torch.float64)
    pegs[:, :, 0] = 40.0 + torch.arange(k_max, dtype=torch.float64)       # unused slots: far away
    pegs[:, :, 2] = 0.01
    r = p.rope_radius
    unit = lambda: float(torch.rand(1, generator=g, dtype=torch.float64))
    for b in range(batch):
        want, slot = 1 + b % k_max, 0
        if b % 2 == 0 and float(delta[b].norm()) > 0:                     # on the drag path
            clipped = diffdlo.planar.control.clip_drag(delta[b:b + 1], p.max_disp)[0]
            slot += place(pos, p, b, pegs, slot, pos[b, node[b]] + (0.3 + 0.4 * unit()) * clipped, 0.004)
        for _ in range(200):
            if slot == want:
                break
            k = int(torch.randint(0, p.n_nodes - 1, (1,), generator=g))
            a, e = pos[b, k], pos[b, k + 1] - pos[b, k]
            side = torch.stack([-e[1], e[0]]) / e.norm() * (1.0 if unit() < 0.5 else -1.0)
            radius = 0.004 + 0.016 * unit()
            centre = a + (0.05 + 0.9 * unit()) * e - side * (radius + r - (0.1 + 0.8 * unit()) * r)
            slot += place(pos, p, b, pegs, slot, centre, radius)
    return pos, node, delta, pin, pegs


def touched(frames, pegs, p):
    """(B,) whether a rope overlapped a peg in any frame."""
    depth = torch.stack([contact.depth(f, pegs, p.rope_radius) for f in frames.detach()])
    return (depth > 0).any(0)


def pair(p, dtype=torch.float64):
    ref = diffdlo.Simulator(p, dtype=dtype, backend="torch")
    fast = diffdlo.Simulator(p, dtype=dtype, backend="kernel")
    assert fast.contact_engine == "kernel" and ref.engine == "torch"
    return ref, fast


# ------------------------------------------------------------------------------------------------ Hessian
def test_kernel_hessian_vector_product_with_pegs_matches_autograd(params):
    """kernel.hvp (the adjoint's H u) with pegs against autograd of the internal plus contact energy, at a state
    with links in the ramp (0 < z < w) and the linear part (z > w) of the penalty, with t inside the link and
    clamped to a node, and with the grasped node's links lifted."""
    p = dataclasses.replace(params, n_nodes=8, length=0.2)
    r, w = p.rope_radius, p.contact_width
    x = torch.stack([torch.arange(8, dtype=torch.float64) * p.rest_length,
                     0.002 * torch.randn(8, generator=torch.Generator().manual_seed(0), dtype=torch.float64)], -1)
    radius = 0.01

    def peg(point, normal, z):                # a peg overlapping the rope by z at point, pushing along normal
        c = point - normal / normal.norm() * (radius + r - z)
        return [float(c[0]), float(c[1]), radius]

    def normal(k, side):
        e = x[k + 1] - x[k]
        return torch.stack([-e[1], e[0]]) * side

    mid = lambda k: 0.5 * (x[k] + x[k + 1])
    pegs = torch.tensor([peg(mid(1), normal(1, 1.0), 0.4 * w),           # interior t, ramp
                         peg(mid(4), normal(4, -1.0), 1.6 * w),          # interior t, linear part
                         peg(x[7], x[6] - x[7], 0.6 * w),                # beyond the end node: t clamped to 1
                         peg(x[0], x[1] - x[0], 2.4 * w)], dtype=torch.float64)   # before the start: t = 0
    t, _, d = contact.closest_points(x[None], pegs[None])
    z = (pegs[None, None, :, 2] + r - d)[0]
    touching = z > 0
    assert ((z > 0) & (z < w)).any() and (z > w).any()
    assert (touching & (t[0] > 0) & (t[0] < 1)).any() and (touching & ((t[0] == 0) | (t[0] == 1))).any()

    def total(xx, lift):
        weight = None if lift < 0 else contact.lifted_links(torch.tensor([lift]), 8, torch.float64)
        return (diffdlo.energy(xx[None], p.rest_length, p.k_s, p.k_b).sum()
                + contact.energy(xx[None], pegs[None], r, p.contact_stiffness, w, weight).sum())

    for lift in (-1, 2, 7):                   # 2: links 1 and 2 lifted (link 1 in contact)
        for seed in range(3):
            u = torch.randn(x.shape, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
            _, expected = torch.autograd.functional.hvp(lambda xx: total(xx, lift), x, u)
            got = kernel.hvp(p, x, u, pegs, lift)
            torch.testing.assert_close(got, expected, rtol=1e-9, atol=1e-9 * float(expected.abs().max()))
            contact_part = got - kernel.hvp(p, x, u)
            assert contact_part.abs().max() > 0.5 * expected.abs().max(), "the contact term must matter"


# ------------------------------------------------------------------------------------------------ forward
@pytest.mark.parametrize("variant", ["default", "fast_path"])
def test_kernel_move_with_pegs_and_pins_equals_eager(params, variant):
    # fast_path: drags that would need more than max_drag_steps substeps go faster than max_speed
    p = short(params) if variant == "default" else short(params, max_drag_steps=100)
    ref, fast = pair(p)
    pos, node, delta, pin, pegs = scene(p, seed=1)
    runs = {}
    for name, (pg, pn) in {"pegs": (pegs, None), "both": (pegs, pin), "pin": (None, pin)}.items():
        a, ia = ref.move(pos, node, delta, pg, pn, return_info=True, record_every=10)
        b, ib = fast.move(pos, node, delta, pg, pn, return_info=True, record_every=10)
        torch.testing.assert_close(b, a, rtol=0, atol=1e-12)
        for key in ("drag_substeps", "settle_substeps", "settled"):
            assert torch.equal(getattr(ib, key), getattr(ia, key)), (name, key)
        assert ib.frames.shape == ia.frames.shape
        torch.testing.assert_close(ib.frames, ia.frames, rtol=0, atol=1e-12)
        runs[name] = (a, ia)
    if variant == "fast_path":
        assert (runs["both"][1].drag_substeps == p.max_drag_steps).sum() > 1
    plain = fast.move(pos, node, delta)
    moved, info = runs["both"]
    # the scenes are in contact, in both lane groups and on the per-rope path
    hit = touched(info.frames, pegs, p)
    assert hit[:LANES].sum() >= LANES - 2 and hit[2 * LANES:].sum() >= 3
    assert (runs["pegs"][0] - plain).norm(dim=-1).amax(-1).gt(1e-4).sum() > BATCH // 2
    # the pins move the result, and hold their node during the drag
    pinned = (pin >= 0) & (info.drag_substeps > 0)
    change = (moved - runs["pegs"][0]).norm(dim=-1).amax(-1)[pinned]
    assert (change > 1e-6).all() and (change > 1e-4).float().mean() > 0.5
    for b in pinned.nonzero().flatten().tolist():
        last = (int(info.drag_substeps[b]) - 1) // 10            # the last frame before the release substep
        torch.testing.assert_close(info.frames[last, b, pin[b]], pos[b, pin[b]], rtol=0, atol=1e-15)
    # a lifted link (at the grasped node) overlaps a peg during some drags: the lift matters there
    lifted = contact.lifted_links(node, p.n_nodes, torch.float64) == 0
    deep = torch.zeros(BATCH, dtype=torch.bool)
    for j in range(1, info.frames.shape[0]):
        dragging = j * 10 <= info.drag_substeps
        z = contact.overlap(info.frames[j], pegs, p.rope_radius).amax(-1)         # (B, L)
        deep |= dragging & ((z > 0) & lifted).any(-1)
    assert deep[:2 * LANES].sum() >= 3 and deep[2 * LANES:].any()


def test_kernel_move_with_shared_pegs_and_free_evolution_equal_eager(params):
    """(K, 3) pegs shared by the batch (the ropes shifted so that each touches the first), and integrate()."""
    p = short(params)
    ref, fast = pair(p)
    pos, node, delta, pin, _ = scene(p, seed=2)
    shared = torch.tensor([[0.0, 0.0, 0.012], [0.05, 0.03, 0.006], [-0.04, 0.05, 0.015]], dtype=torch.float64)
    r = p.rope_radius
    g = torch.Generator().manual_seed(3)
    for b in range(BATCH):                     # shift rope b so that a link touches peg 0, clear of the others
        for _ in range(100):
            k = int(torch.randint(0, p.n_nodes - 1, (1,), generator=g))
            e = pos[b, k + 1] - pos[b, k]
            side = torch.stack([-e[1], e[0]]) / e.norm()
            point = pos[b, k] + 0.5 * e + side * (shared[0, 2] + r - 0.5 * r)
            moved = pos[b] - point
            if float(contact.overlap(moved[None], shared[None], r).max()) <= 0.9 * r:
                pos[b] = moved
                break
        else:
            raise AssertionError(f"no place for rope {b}")
    a, ia = ref.move(pos, node, delta, shared, pin, return_info=True, record_every=25)
    b, ib = fast.move(pos, node, delta, shared, pin, return_info=True, record_every=25)
    torch.testing.assert_close(b, a, rtol=0, atol=1e-12)
    assert torch.equal(ia.substeps, ib.substeps) and torch.equal(ia.settled, ib.settled)
    assert touched(ia.frames, shared.expand(BATCH, 3, 3), p).all()
    vel = 0.01 * torch.randn(pos.shape, generator=g, dtype=torch.float64)
    free_ref = ref.integrate(pos, vel, 120, pegs=shared)
    free = fast.integrate(pos, vel, 120, pegs=shared)
    for x, y in zip(free, free_ref):
        torch.testing.assert_close(x, y, rtol=0, atol=1e-12)
    assert (free[0] - fast.integrate(pos, vel, 120)[0]).abs().max() > 1e-4


def test_lane_groups_equal_the_per_rope_path_over_full_moves(params):
    """Full-length moves (up to 2000 substeps, where the candidate lists are rebuilt and the lane groups skip
    pairs by their clearance) give the per-rope path's result, which evaluates every candidate each substep."""
    p = params
    pos, node, delta, pin, pegs = scene(p, batch=2 * LANES, seed=4, drag=0.1)
    clipped = diffdlo.planar.control.clip_drag(delta, p.max_disp)
    dist = clipped.norm(dim=-1)
    speed, steps = diffdlo.planar.control.drag_speed(dist, p), diffdlo.planar.control.path_substeps(dist, p)
    out = [kernel.forward(kernel.Setup(p, 2 * LANES, lane_groups=groups, record_every=40), pos, None, node, clipped,
                          speed, steps, None, pegs, pin) for groups in (True, False)]
    for x, y in zip(out[0][:5], out[1][:5]):
        torch.testing.assert_close(x, y, rtol=0, atol=1e-13)
    frames = kernel.assemble_frames(40, out[0][5], out[0][0], out[0][2], False)
    assert touched(frames, pegs, p).sum() > LANES


# ------------------------------------------------------------------------------------------------ gradients
def run(p, backend, pos, vel, node, delta, pegs, pin, factors, record_every=7):
    """One move with physics factors * nominal (B,) tensors; values and gradients of a loss over the final pos and
    the frames w.r.t. pos, vel, delta and the four physics tensors."""
    sim = diffdlo.Simulator(p, dtype=torch.float64, backend=backend)
    values = [(f * float(getattr(p, k))).clone().requires_grad_(True) for f, k in zip(factors.unbind(-1), PHYSICAL)]
    x, v, d = (t.clone().requires_grad_(True) for t in (pos, vel, delta))
    out, info = sim.move(x, node, d, pegs, pin, vel=v, physics=Physics(*values), return_info=True,
                         record_every=record_every, differentiable_frames=True)
    weight = torch.linspace(0.5, 1.5, info.frames.shape[0], dtype=torch.float64).view(-1, 1, 1, 1)
    loss = (out ** 2).sum() + out[:, 2].sum() + (weight * (info.frames - 0.01) ** 2).sum()
    return out.detach(), info, torch.autograd.grad(loss, (x, v, d, *values))


def test_kernel_gradients_with_pegs_pins_physics_and_frames_equal_eager(rope8):
    p = rope8
    pos, node, delta, pin, pegs = scene(p, seed=5, drag=0.04)
    g = torch.Generator().manual_seed(6)
    vel = 0.01 * torch.randn(pos.shape, generator=g, dtype=torch.float64)
    factors = torch.exp((torch.rand(BATCH, 4, generator=g, dtype=torch.float64) * 2 - 1) * 0.5)
    ref_out, ref_info, ref_grads = run(p, "torch", pos, vel, node, delta, pegs, pin, factors)
    out, info, grads = run(p, "kernel", pos, vel, node, delta, pegs, pin, factors)
    torch.testing.assert_close(out, ref_out, rtol=0, atol=1e-12)
    assert torch.equal(info.substeps, ref_info.substeps)
    hit = touched(ref_info.frames, pegs, p)
    assert hit[:2 * LANES].sum() > LANES and hit[2 * LANES:].sum() >= 3
    names = ("pos", "vel", "delta", *PHYSICAL)
    for name, a, b in zip(names, grads, ref_grads):
        scale = float(b.abs().max())
        assert scale > 0, name
        assert float((a - b).abs().max()) <= 1e-7 * scale, (name, float((a - b).abs().max()), scale)
    # the contact matters to the gradients: without pegs they differ
    _, _, free_grads = run(p, "kernel", pos, vel, node, delta, None, pin, factors)
    assert (free_grads[0] - grads[0]).abs().max() > 1e-2 * grads[0].abs().max()


@pytest.mark.parametrize("size", [2, LANES + 1])
def test_gradcheck_kernel_move_in_contact_with_a_pin(params, size):
    p = dataclasses.replace(params, n_nodes=5, length=0.12, max_speed=1.0, settle_threshold=0.0,
                            settle_check_every=5, settle_max_substeps=15)
    sim = diffdlo.Simulator(p, dtype=torch.float64, backend="kernel")
    pos, node, delta, pin, pegs = scene(p, batch=size, seed=7, k_max=2, drag=0.02, special=False)   # |delta| > 0
    pin[:] = torch.where(node == 0, 4, 0)
    hit = touched(sim.move(pos, node, delta, pegs, pin, return_info=True, record_every=1)[1].frames, pegs, p)
    assert hit.all()

    def moved(x, d):
        return sim.move(x, node, d, pegs, pin)

    leaves = (pos.clone().requires_grad_(True), delta.clone().requires_grad_(True))
    assert torch.autograd.gradcheck(moved, leaves, eps=1e-7, atol=1e-7, rtol=1e-4)


# ------------------------------------------------------------------------------------------------ float32
def test_float32_kernel_with_pegs_near_the_float64_eager_path(params):
    p = short(params, settle_threshold=0.0)         # every rope runs to the cap: the same substeps in float32
    pos, node, delta, pin, pegs = scene(p, seed=8)
    ref = diffdlo.Simulator(p, dtype=torch.float64, backend="torch")
    fast = diffdlo.Simulator(p, dtype=torch.float32, backend="kernel")
    a = ref.move(pos, node, delta, pegs, pin)
    b = fast.move(pos.float(), node, delta.float(), pegs.float(), pin).double()
    assert (b - a).norm(dim=-1).max() < 1e-4


# ------------------------------------------------------------------------------------------------ unchanged
def test_no_pegs_and_no_pin_run_the_plain_kernel(params):
    p = short(params)
    sim = diffdlo.Simulator(p, dtype=torch.float64)
    assert sim.engine == "kernel" and sim.contact_engine == "kernel" and "contact" not in sim.why_not
    pos, node, delta, pin, _ = scene(p, seed=9)
    plain = sim.move(pos, node, delta)
    empty = torch.zeros(0, 3, dtype=torch.float64)
    assert torch.equal(sim.move(pos, node, delta, empty), plain)
    assert torch.equal(sim.move(pos, node, delta, None, torch.full_like(pin, -1)), plain)
    assert torch.equal(sim.integrate(pos, None, 50, pegs=empty)[0], sim.integrate(pos, None, 50)[0])
    clipped = diffdlo.planar.control.clip_drag(delta, p.max_disp)
    dist = clipped.norm(dim=-1)
    control = diffdlo.planar.control
    args = (pos, None, node, clipped, control.drag_speed(dist, p), control.path_substeps(dist, p))
    setup = kernel.Setup(p, BATCH)
    base = kernel.forward(setup, *args)
    for pegs, pins in ((torch.zeros(BATCH, 0, 3, dtype=torch.float64), None), (None, torch.full_like(pin, -1))):
        other = kernel.forward(setup, *args, None, pegs, pins)
        assert all(torch.equal(x, y) for x, y in zip(other[:5], base[:5]))
