"""The fused kernel with per-rope physics (diffdlo.planar.physics) and frame recording, against the eager torch path:
positions, every recorded frame, run statistics, and the gradients w.r.t. pos, delta and k_s, k_b, k_d, mass
(also with a loss over the frames); gradcheck of the kernel's adjoint; physics=None stays the plain fast path."""
import dataclasses

import pytest
import torch

import diffdlo
from diffdlo.planar.backends import kernel
from diffdlo.planar.physics import PHYSICAL, Physics
from tests.conftest import crumpled

pytestmark = pytest.mark.skipif(not kernel.available(), reason=f"kernel unavailable: {kernel.unavailable_reason()}")

# One full vectorized lane group plus three ropes on the per-rope path.
MIXED = (kernel.lanes() + 3) if kernel.available() else 19


@pytest.fixture(autouse=True)
def _one_thread(one_thread):
    """Both paths on one torch thread (the kernel's own threads follow torch's count)."""


@pytest.fixture(scope="module")
def tiny():
    """As in tests/test_physics.py: 4 nodes, a fixed settle (threshold 0), for gradcheck."""
    return dataclasses.replace(diffdlo.load_params(), n_nodes=4, length=0.09, max_speed=1.0, settle_max_substeps=12,
                               settle_check_every=4, settle_threshold=0.0)


@pytest.fixture(scope="module")
def mixed(small):
    """The 6-node rope with a settle that stops some ropes early (at different checks) and others at the cap."""
    return dataclasses.replace(small, settle_threshold=0.03, settle_max_substeps=60)


def batch(p, size=MIXED, seed=0, drag=0.03, settle_only=True):
    """Start shapes, actions and per-rope factors on the params' physics (log-uniform in [1/2, 2]); rope 1 only
    settles (a zero drag, where the drag's norm has a kink) if ``settle_only``."""
    g = torch.Generator().manual_seed(seed)
    pos = crumpled(size, p, sigma=0.5, seed=seed + 1)
    node = torch.randint(0, p.n_nodes, (size,), generator=g)
    delta = (torch.rand(size, 2, generator=g, dtype=torch.float64) * 2 - 1) * drag
    if settle_only:
        delta[1] = 0.0
    factors = torch.exp((torch.rand(size, 4, generator=g, dtype=torch.float64) * 2 - 1) * 0.7)
    return pos, node, delta, factors


def nominal(p):
    return torch.tensor([float(getattr(p, k)) for k in PHYSICAL], dtype=torch.float64)


def run(p, backend, pos, node, delta, factors, record_every, differentiable=True, frame_weight=None):
    """One move with physics exp(theta) * factors * nominal at theta = 0; returns values and gradients of a loss
    over the final pos and (if differentiable) the frames, w.r.t. pos, delta and theta."""
    sim = diffdlo.Simulator(p, dtype=torch.float64, backend=backend)
    theta = torch.zeros(pos.shape[0], 4, dtype=torch.float64, requires_grad=True)
    values = torch.exp(theta) * factors * nominal(p)
    x, d = pos.clone().requires_grad_(True), delta.clone().requires_grad_(True)
    out, info = sim.move(x, node, d, physics=Physics(*values.unbind(-1)), return_info=True,
                         record_every=record_every, differentiable_frames=differentiable)
    loss = (out ** 2).sum() + out[:, 2].sum()
    if differentiable:
        weight = frame_weight if frame_weight is not None else torch.linspace(0.5, 1.5, info.frames.shape[0],
                                                                              dtype=torch.float64)
        loss = loss + (weight.view(-1, 1, 1, 1) * (info.frames - 0.01) ** 2).sum() + info.frames[..., 0].sum()
    grads = torch.autograd.grad(loss, (x, d, theta))
    return out.detach(), info, grads


def assert_mixed_settle(p, info):
    lanes = kernel.lanes()
    for part in (slice(0, lanes), slice(lanes, None)):
        settled, steps = info.settled[part], info.settle_substeps[part]
        assert settled.any() and (~settled).any(), f"settled: {info.settled}"
        assert (steps[~settled] == p.settle_max_substeps).all()
    assert len(set(info.substeps.tolist())) > 5, "the ropes must stop at many different substeps"


@pytest.mark.parametrize("record_every", [7, 1])       # 1: the last frame is the final pos (no extra frame)
def test_kernel_equals_eager_with_per_rope_physics_and_frames(mixed, record_every):
    pos, node, delta, factors = batch(mixed)
    ref_out, ref_info, ref_grads = run(mixed, "torch", pos, node, delta, factors, record_every)
    out, info, grads = run(mixed, "kernel", pos, node, delta, factors, record_every)
    assert_mixed_settle(mixed, ref_info)
    for key in ("drag_substeps", "settle_substeps", "settled"):
        assert torch.equal(getattr(info, key), getattr(ref_info, key)), key
    assert info.frames.shape == ref_info.frames.shape
    torch.testing.assert_close(out, ref_out, rtol=1e-9, atol=1e-13)
    torch.testing.assert_close(info.frames.detach(), ref_info.frames.detach(), rtol=1e-9, atol=1e-13)
    for g, g_ref, name in zip(grads, ref_grads, ("pos", "delta", "theta")):
        assert g_ref.abs().max() > 1e-3, name
        torch.testing.assert_close(g, g_ref, rtol=1e-7, atol=1e-9 * float(g_ref.abs().max()), msg=name)


def test_detached_frames_match_the_eager_path(mixed):
    """Detached frames: the eager loop appends the final pos even when the last frame already is it."""
    pos, node, delta, factors = batch(mixed, seed=4)
    physics = Physics(*(factors * nominal(mixed)).unbind(-1))
    _, info = diffdlo.Simulator(mixed, dtype=torch.float64).move(pos, node, delta, physics=physics, return_info=True)
    last = int(info.substeps.max())
    every = next(k for k in range(5, last + 1) if last % k == 0)          # a frame falls on the last substep
    _, ref_info, _ = run(mixed, "torch", pos, node, delta, factors, every, differentiable=False)
    _, info, _ = run(mixed, "kernel", pos, node, delta, factors, every, differentiable=False)
    assert ref_info.frames.shape[0] == last // every + 2
    assert info.frames.shape == ref_info.frames.shape and not info.frames.requires_grad
    torch.testing.assert_close(info.frames, ref_info.frames, rtol=1e-9, atol=1e-13)


def test_kernel_gradient_over_frames_equals_eager_autograd_on_the_small_rope(small):
    pos, node, delta, factors = batch(small, seed=7)
    ref_out, ref_info, ref_grads = run(small, "torch", pos, node, delta, factors, 5)
    out, info, grads = run(small, "kernel", pos, node, delta, factors, 5)
    torch.testing.assert_close(info.frames.detach(), ref_info.frames.detach(), rtol=1e-9, atol=1e-13)
    for g, g_ref, name in zip(grads, ref_grads, ("pos", "delta", "theta")):
        torch.testing.assert_close(g, g_ref, rtol=1e-7, atol=1e-9 * float(g_ref.abs().max()), msg=name)


@pytest.mark.parametrize("size", [2, MIXED])
@pytest.mark.parametrize("target", ["frames", "final"])
def test_gradcheck_kernel_move_in_log_physics(tiny, size, target):
    sim = diffdlo.Simulator(tiny, dtype=torch.float64, backend="kernel")
    pos, node, delta, factors = batch(tiny, size=size, seed=3, drag=0.005, settle_only=False)
    scale = factors * nominal(tiny)

    def moved(x, d, *log_values):                  # log-parametrized, as a calibration fits them
        values = [torch.exp(v) * s for v, s in zip(log_values, scale.unbind(-1))]
        out, info = sim.move(x, node, d, physics=Physics(*values), return_info=True, record_every=3,
                             differentiable_frames=True)
        return info.frames if target == "frames" else out

    leaves = (pos.clone().requires_grad_(True), delta.clone().requires_grad_(True),
              *(torch.zeros(size, dtype=torch.float64, requires_grad=True) for _ in PHYSICAL))
    # eps 1e-7: the release share phi varies on the scale max_speed dt (1 mm here), so a 1e-6 step's truncation
    # error (~2e-7 on an entry of 0.94, measured) exceeds atol; at 1e-7 it is ~2e-9
    assert torch.autograd.gradcheck(moved, leaves, eps=1e-7, atol=1e-8, rtol=1e-4)


def test_gradcheck_kernel_free_evolution_in_physics_with_float_values(tiny):
    """Floats need no gradient; a 0-dim tensor is shared by all ropes; the velocity output carries one too."""
    sim = diffdlo.Simulator(tiny, dtype=torch.float64, backend="kernel")
    pos, _, _, factors = batch(tiny, size=MIXED, seed=5)
    vel = 0.01 * torch.randn(pos.shape, generator=torch.Generator().manual_seed(6), dtype=torch.float64)

    def evolve(log_k_s, log_k_d, log_mass):
        physics = Physics(torch.exp(log_k_s) * factors[:, 0] * tiny.k_s, tiny.k_b * 2.0,
                          torch.exp(log_k_d) * tiny.k_d, torch.exp(log_mass) * factors[:, 3] * tiny.mass)
        x, v = sim.integrate(pos, vel, 15, physics=physics)
        return x, 1e-3 * v

    leaves = (torch.zeros(MIXED, dtype=torch.float64, requires_grad=True),
              torch.zeros((), dtype=torch.float64, requires_grad=True),
              torch.zeros(MIXED, dtype=torch.float64, requires_grad=True))
    assert torch.autograd.gradcheck(evolve, leaves, eps=1e-6, atol=1e-8, rtol=1e-4)


def test_kernel_free_evolution_with_physics_equals_eager(mixed):
    pos, _, _, factors = batch(mixed, seed=8)
    vel = 0.01 * torch.randn(pos.shape, generator=torch.Generator().manual_seed(9), dtype=torch.float64)
    results = []
    for backend in ("torch", "kernel"):
        sim = diffdlo.Simulator(mixed, dtype=torch.float64, backend=backend)
        theta = torch.zeros(MIXED, 4, dtype=torch.float64, requires_grad=True)
        x, v = pos.clone().requires_grad_(True), vel.clone().requires_grad_(True)
        values = torch.exp(theta) * factors * nominal(mixed)
        out_x, out_v = sim.integrate(x, v, 40, physics=Physics(*values.unbind(-1)))
        grads = torch.autograd.grad((out_x ** 2).sum() + out_v.sum(), (x, v, theta))
        results.append((out_x.detach(), out_v.detach(), *grads))
    for a, b in zip(*results):
        torch.testing.assert_close(b, a, rtol=1e-9, atol=1e-12)


def test_float32_kernel_with_physics_and_frames_near_the_float64_reference(mixed):
    pos, node, delta, factors = batch(mixed, seed=10)
    physics = Physics(*(factors * nominal(mixed)).unbind(-1))
    ref = diffdlo.Simulator(mixed, dtype=torch.float64, backend="torch")
    fast = diffdlo.Simulator(mixed, dtype=torch.float32, backend="kernel")
    a, ia = ref.move(pos, node, delta, physics=physics, return_info=True, record_every=5)
    b, ib = fast.move(pos.float(), node, delta.float(), physics=physics, return_info=True, record_every=5)
    if torch.equal(ia.substeps, ib.substeps):          # float32 may settle at another check: compare when not
        assert (ib.frames.double() - ia.frames).abs().max() < 1e-4
    assert (b.double() - a).norm(dim=-1).max() < 1e-3


def test_physics_none_and_no_frames_is_the_plain_kernel_path(mixed):
    """physics=None, record_every=0 runs the scalar kernel (equal to the eager path as tests/test_kernel.py
    checks); the params' own numbers as per-rope physics give the very same bits."""
    pos, node, delta, _ = batch(mixed, seed=11)
    sim = diffdlo.Simulator(mixed, dtype=torch.float64)
    assert sim.engine == "kernel"
    plain, info = sim.move(pos, node, delta, return_info=True)
    assert info.frames is None
    ref = diffdlo.Simulator(mixed, dtype=torch.float64, backend="torch").move(pos, node, delta)
    torch.testing.assert_close(plain, ref, rtol=0, atol=1e-12)
    for physics in (Physics.of(mixed, MIXED), Physics(*(float(getattr(mixed, k)) for k in PHYSICAL))):
        assert torch.equal(sim.move(pos, node, delta, physics=physics), plain)
    recorded, info = sim.move(pos, node, delta, return_info=True, record_every=5)
    assert torch.equal(recorded, plain) and info.frames.shape[1:] == pos.shape


@pytest.mark.parametrize("max_settle", [60, 0])     # 0: the cap stops the rope on its release substep
def test_gradient_through_the_returned_state_equals_eager(mixed, max_settle):
    """A loss on the returned positions and velocities: the kernel's adjoint of the release within the drag's last
    substep and of the settle cap's share (control.last_substep_fraction) equals autograd of the eager loop, also
    for the velocities (which Simulator.move does not return) and with a cap that ends on the release substep."""
    p = dataclasses.replace(mixed, settle_max_substeps=max_settle)
    pos, node, delta, _ = batch(p)
    sim = diffdlo.Simulator(p, dtype=torch.float64, backend="kernel")
    clipped = diffdlo.planar.control.clip_drag(delta, p.max_disp)
    steps = diffdlo.planar.control.path_substeps(clipped.norm(dim=-1), p)
    weights = torch.randn(2, *pos.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(5))
    grads, capped = [], None
    for engine in ("torch", "kernel"):
        x, v, d = (t.clone().requires_grad_(True) for t in (pos, 0.01 * weights[1], clipped))
        speed = diffdlo.planar.control.drag_speed(d.norm(dim=-1), p)
        if engine == "torch":
            out_x, out_v, _, _, settled, _ = sim._move_eager(x, v, node, d, speed, steps)
            capped = ~settled
        else:
            out_x, out_v, *_ = sim._kernel_apply(x, v, node, d, speed.detach(), steps, None)
        loss = (out_x * weights[0]).sum() + (out_v * weights[1]).sum()
        grads.append(torch.autograd.grad(loss, (x, v, d)))
    assert int(capped.sum()) >= 3                                  # ropes stopped by the cap: their share applies
    for name, a, b in zip(("pos", "vel", "delta"), *grads):
        assert (a - b).abs().max().item() < 1e-9 * a.abs().max().item(), name
