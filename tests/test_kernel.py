"""The fused C++ kernel against the pure-torch reference path: positions, run statistics and gradients."""
import dataclasses

import pytest
import torch

import diffdlo
from diffdlo.planar.backends import kernel
from conftest import crumpled

pytestmark = pytest.mark.skipif(not kernel.available(), reason=f"kernel unavailable: {kernel.unavailable_reason()}")

# Batches of one full vectorized lane group plus a few ropes on the per-rope path exercise both code paths.
MIXED = (kernel.lanes() + 3) if kernel.available() else 19


def short(p, **changes):
    """Fewer substeps, same phases: a drag takes at most 334 substeps (0.3 m/s), the settle is checked every 50
    substeps up to 300, and its 0.02 m/s threshold stops some ropes early while others reach the cap."""
    return dataclasses.replace(p, max_speed=0.3, settle_threshold=0.02, settle_check_every=50,
                               settle_max_substeps=300, **changes)


def assert_mixed_settle(p, *infos):
    """Over the moves' infos, some ropes stop early and some reach the cap, both in the vectorized lane group and
    on the per-rope path."""
    lanes = kernel.lanes()
    settled = torch.stack([info.settled for info in infos])
    steps = torch.stack([info.settle_substeps for info in infos])
    for part in (slice(0, lanes), slice(lanes, None)):
        done, n = settled[:, part], steps[:, part]
        assert (n[~done] == p.settle_max_substeps).all() and (~done).any(), f"settled: {settled}"
        assert (n[done] < p.settle_max_substeps).any(), f"settle substeps: {steps}"


def pair(p, dtype=torch.float64):
    return (diffdlo.Simulator(p, dtype=dtype, backend="torch"), diffdlo.Simulator(p, dtype=dtype, backend="kernel"))


def actions(batch, seed=0, scale=0.1, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    node = torch.randint(0, 20, (batch,), generator=g)
    delta = ((torch.rand(batch, 2, generator=g, dtype=torch.float64) * 2 - 1) * scale).to(dtype)
    return node, delta


@pytest.mark.parametrize("variant", ["default", "fast_path"])
def test_kernel_move_equals_reference_with_gradients(params, variant):
    # fast_path: a drag that would need more than max_drag_steps substeps goes faster than max_speed
    p = short(params) if variant == "default" else short(params, max_drag_steps=100)
    ref, fast = pair(p)
    # one lane group (vectorized across ropes) and 3 ropes on the per-rope path
    pos = crumpled(MIXED, params, sigma=0.3, seed=1)
    node, delta = actions(MIXED, seed=2)
    delta[MIXED - 2] = 0.0
    delta[0] = 0.0                                    # no drag at all: settle only
    delta[1] = torch.tensor([0.3, -0.2], dtype=torch.float64)      # clipped to max_disp
    assert fast.engine == "kernel" and ref.engine != "kernel"
    a, ia = ref.move(pos, node, delta, return_info=True)
    b, ib = fast.move(pos, node, delta, return_info=True)
    torch.testing.assert_close(b, a, rtol=0, atol=1e-12)
    assert torch.equal(ia.drag_substeps, ib.drag_substeps) and torch.equal(ia.settle_substeps, ib.settle_substeps)
    assert torch.equal(ia.settled, ib.settled)
    assert_mixed_settle(p, ia)
    if variant == "fast_path":
        assert (ia.drag_substeps == p.max_drag_steps).sum() > 1, "some drags must go faster than max_speed"
    target = diffdlo.target_shape("antidiagonal", p, dtype=torch.float64)
    grads = []
    for sim in (ref, fast):
        x, d = pos.clone().requires_grad_(True), delta.clone().requires_grad_(True)
        moved = sim.move(x, node, d)
        loss = diffdlo.shape_error(moved, target).sum() + moved[:, 3].pow(2).sum()
        grads.append(torch.autograd.grad(loss, (x, d)))
    for g_ref, g_fast in zip(*grads):
        assert g_ref.abs().max() > 1e-3
        torch.testing.assert_close(g_fast, g_ref, rtol=1e-9, atol=1e-11)


def test_kernel_hessian_vector_product_matches_autograd(params):
    pos = crumpled(1, params, sigma=1.4, seed=3)[0] * 1.03
    u = torch.randn(pos.shape, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    x = pos.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(diffdlo.energy(x[None], params.rest_length, params.k_s, params.k_b).sum(), x,
                                  create_graph=True)
    (expected,) = torch.autograd.grad((grad * u).sum(), x)
    torch.testing.assert_close(kernel.hvp(params, pos, u), expected, rtol=1e-9, atol=1e-10)


@pytest.mark.parametrize("batch", [2, MIXED])
def test_gradcheck_kernel_move(params, batch):
    p = dataclasses.replace(params, n_nodes=6, length=0.15, max_speed=1.0, settle_threshold=0.0,
                            settle_check_every=10, settle_max_substeps=30)
    sim = diffdlo.Simulator(p, dtype=torch.float64, backend="kernel")
    pos = crumpled(batch, p, sigma=0.8, seed=2).requires_grad_(True)
    g = torch.Generator().manual_seed(3)
    delta = ((torch.rand(batch, 2, generator=g, dtype=torch.float64) - 0.5) * 0.03).requires_grad_(True)
    node = torch.randint(0, 6, (batch,), generator=g)
    assert torch.autograd.gradcheck(lambda x, d: sim.move(x, node, d), (pos, delta), eps=1e-7, atol=1e-6,
                                    rtol=1e-4)


def test_kernel_free_evolution_equals_reference(params):
    ref, fast = pair(params)
    pos = crumpled(MIXED, params, sigma=0.5, seed=5) * 1.02
    vel = 0.01 * torch.randn(pos.shape, generator=torch.Generator().manual_seed(6), dtype=torch.float64)
    grads = []
    for sim in (ref, fast):
        x, v = pos.clone().requires_grad_(True), vel.clone().requires_grad_(True)
        out_x, out_v = sim.integrate(x, v, 150)
        grads.append((out_x.detach(), out_v.detach(), *torch.autograd.grad((out_x ** 2).sum() + out_v.sum(), (x, v))))
    for a, b in zip(*grads):
        torch.testing.assert_close(b, a, rtol=1e-9, atol=1e-11)
    same_x, same_v = fast.integrate(pos, vel, 0)
    assert torch.equal(same_x, pos) and torch.equal(same_v, vel)


def test_float32_kernel_within_1mm_of_the_float64_reference(params):
    """The kernel's accuracy bar: after one move and after 1 s of free evolution."""
    ref = diffdlo.Simulator(params, dtype=torch.float64, backend="torch")
    fast = diffdlo.Simulator(params, dtype=torch.float32, backend="kernel")
    pos = crumpled(MIXED, params, sigma=0.3, seed=7)
    node, delta = actions(MIXED, seed=8)
    moved = fast.move(pos.float(), node, delta.float()).double()
    assert (moved - ref.move(pos, node, delta)).norm(dim=-1).max() < 1e-3
    free = fast.integrate(pos.float(), None, 1000)[0].double()
    assert (free - ref.integrate(pos, None, 1000)[0]).norm(dim=-1).max() < 1e-3


@pytest.mark.parametrize("batch,bad", [(2, 0), (MIXED, 3), (MIXED, MIXED - 1)])
def test_kernel_reports_divergence(params, batch, bad):
    pos = crumpled(batch, params)
    pos[bad, 5] = pos[bad, 4] + torch.tensor([1e3, 0.0], dtype=torch.float64)   # a link 1 km long: it blows up
    with pytest.raises(diffdlo.SimulationError, match=rf"batch members \[{bad}\]"):
        diffdlo.Simulator(params, dtype=torch.float64, backend="kernel").move(
            pos, torch.zeros(batch, dtype=torch.int64), torch.zeros(batch, 2, dtype=torch.float64))


def test_backend_selection_and_fallback(params, monkeypatch):
    assert diffdlo.Simulator(params).engine == "kernel"
    assert diffdlo.Simulator(params).engine == "kernel"                       # frames run in the kernel too
    assert diffdlo.Simulator(dataclasses.replace(params, controller="pid")).engine != "kernel"
    with pytest.raises(ValueError, match="kinematic controller only"):
        diffdlo.Simulator(dataclasses.replace(params, controller="pid"), backend="kernel")
    with pytest.raises(ValueError, match="backend must be one of"):
        diffdlo.Simulator(params, backend="fast")
    monkeypatch.setattr(kernel._library, "lib", None)
    monkeypatch.setattr(kernel._library, "error", "no C++ compiler found (set $CXX or install g++)")
    with pytest.raises(RuntimeError, match="backend 'kernel' is unavailable: no C\\+\\+ compiler"):
        diffdlo.Simulator(params, backend="kernel")
    sim = diffdlo.Simulator(params)                   # auto falls back to the torch path
    assert sim.engine != "kernel"
    pos = sim.random_shape(1, torch.Generator().manual_seed(0))
    assert sim.move(pos, torch.tensor([0]), torch.tensor([[0.01, 0.0]])).shape == pos.shape


def test_gradient_of_a_move_sequence_equals_plain_autograd(params):
    """The memory-bounded gradient of several moves equals autograd through the eager loop."""
    p = short(params)
    ref, fast = pair(p)
    pos = crumpled(MIXED, params, sigma=0.3, seed=9)
    g = torch.Generator().manual_seed(10)
    nodes = [torch.randint(0, 20, (MIXED,), generator=g) for _ in range(3)]
    deltas = (torch.rand(3, MIXED, 2, generator=g, dtype=torch.float64) * 2 - 1) * 0.08
    target = diffdlo.target_shape("vertical", p, dtype=torch.float64)
    grads = []
    for sim in (ref, fast):
        x0, d = pos.clone().requires_grad_(True), deltas.clone().requires_grad_(True)
        x, infos = x0, []
        for m in range(3):
            x, info = sim.move(x, nodes[m], d[m], return_info=True)
            infos.append(info)
        assert_mixed_settle(p, *infos)
        grads.append(torch.autograd.grad(diffdlo.shape_error(x, target).sum(), (x0, d)))
    for g_ref, g_fast in zip(*grads):
        torch.testing.assert_close(g_fast, g_ref, rtol=1e-8, atol=1e-10)
