"""The fused Triton kernel (backend "triton", diffdlo/planar/backends/triton_kernel.py) against the eager torch
reference path.

Marked ``triton`` (kept out of the default run; .ci/run runs them after installing the [gpu] extra):
``TRITON_INTERPRET=1 python -m pytest -m triton`` runs the kernels (the move and its adjoint) in Triton's CPU
interpreter; on a machine with CUDA the same tests run the compiled kernels on the GPU. The interpreter takes ~20-30
ms per substep, so the params are cut to ~100-substep moves. The gradient problem is
benchmarks/gradients/triton_gradients.py's, which prints the errors the test bounds.
"""
import dataclasses
import os
import subprocess
import sys

import pytest
import torch

import diffdlo
from conftest import crumpled

triton = pytest.importorskip("triton")
from benchmarks.contact_checks import line  # noqa: E402
from benchmarks.gradients import triton_gradients  # noqa: E402
from diffdlo.planar.backends import triton_kernel  # noqa: E402

pytestmark = pytest.mark.triton

DEVICE = "cuda" if torch.cuda.is_available() else "cpu"
if DEVICE == "cpu" and not triton_kernel.interpreting():
    pytestmark = [pytest.mark.triton,
                  pytest.mark.skip(reason="no CUDA device: run with TRITON_INTERPRET=1 to test in the interpreter")]


short = triton_gradients.short_params


def sims(p, dtype):
    return (diffdlo.Simulator(p, device=DEVICE, dtype=dtype, backend="torch"),
            diffdlo.Simulator(p, device=DEVICE, dtype=dtype, backend="triton"))


def problem(p, dtype):
    batch = 5
    pos = crumpled(batch, p, sigma=0.8, seed=3).to(DEVICE, dtype)
    straight = torch.stack([torch.linspace(-0.25, 0.25, p.n_nodes, dtype=torch.float64),
                            torch.zeros(p.n_nodes, dtype=torch.float64)], -1)
    pos[3] = straight.to(DEVICE, dtype)                        # at rest, no drag: settles at the first check
    node = torch.tensor([0, 5, 19, 7, 12], device=DEVICE)
    delta = torch.tensor([[0.05, 0.0], [0.0, -0.08], [0.3, 0.2], [0.0, 0.0], [0.004, 0.01]],
                         dtype=dtype, device=DEVICE)            # [2] is clipped to max_disp
    return pos, node, delta


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 1e-3)])
def test_move_matches_eager(params, dtype, tol):
    p = short(params)
    ref, tri = sims(p, dtype)
    assert tri.engine == "triton" and ref.engine != "triton" and tri.engine != "kernel"
    pos, node, delta = problem(p, dtype)
    vel = torch.zeros_like(pos)
    vel[0, 4] = torch.tensor([0.01, -0.02], dtype=dtype)
    a, ia = ref.move(pos, node, delta, vel=vel, return_info=True)
    b, ib = tri.move(pos, node, delta, vel=vel, return_info=True)
    assert b.device == pos.device and b.dtype == dtype
    assert (a - b).norm(dim=-1).max().item() < tol
    assert torch.equal(ia.drag_substeps, ib.drag_substeps)
    assert torch.equal(ia.settle_substeps, ib.settle_substeps)
    assert torch.equal(ia.settled, ib.settled)
    assert bool(ib.settled[3]) and not bool(ib.settled[0])      # one rope settles early, one runs to the cap
    assert int(ib.substeps[3]) == p.settle_check_every and int(ib.substeps[0]) > p.settle_max_substeps
    # final velocities, from the kernel's raw outputs
    clipped = diffdlo.planar.control.clip_drag(delta, p.max_disp)
    steps = diffdlo.planar.control.path_substeps(clipped.norm(dim=-1), p)
    _, vb, *_ = tri._triton_apply(pos, vel, node, clipped, steps, -1, None)
    speed = diffdlo.planar.control.drag_speed(clipped.norm(dim=-1), p)
    va = ref._move_eager(pos, vel, node, clipped, speed, steps)[1]
    assert (va - vb).norm(dim=-1).max().item() < tol * 10


def test_integrate_matches_eager_with_physics(params):
    p = short(params)
    ref, tri = sims(p, torch.float64)
    pos = crumpled(3, p, sigma=0.8, seed=5).to(DEVICE)
    phys = diffdlo.Physics(k_s=torch.tensor([999.0, 600.0, 1200.0], dtype=torch.float64, device=DEVICE),
                           k_b=0.02, k_d=torch.tensor([100.0, 80.0, 120.0], dtype=torch.float64, device=DEVICE),
                           mass=0.2)
    for physics in (None, phys):
        a = ref.integrate(pos, None, 30, physics=physics)
        b = tri.integrate(pos, None, 30, physics=physics)
        for u, v in zip(a, b):
            assert (u - v).abs().max().item() < 1e-12


@pytest.mark.parametrize("dtype,rtol", [(torch.float64, 1e-6), (torch.float32, 1e-4)])
def test_gradients_match_eager(params, dtype, rtol):
    """The Triton adjoint against autograd through the eager loop, in the same dtype: every input, whole and chained
    moves, per-rope stops; relative to each gradient's largest entry."""
    p = short(params, max_speed=1.0)                  # drags longer than 4 cm run faster than max_speed
    ref, tri = sims(p, dtype)
    problem_ = triton_gradients.gradient_problem(p, dtype, DEVICE)
    info_ref, g_ref = triton_gradients.chained_gradients(ref, *problem_)
    info_tri, g_tri = triton_gradients.chained_gradients(tri, *problem_)
    assert torch.equal(info_ref.substeps, info_tri.substeps.to(info_ref.substeps.device))
    steps = info_tri.substeps.tolist()
    assert steps[6] == p.settle_check_every and steps[3] == p.settle_max_substeps and steps[0] > steps[3], steps
    for name, a, b in zip(triton_gradients.INPUTS, g_ref, g_tri):
        assert torch.isfinite(b).all() and b.abs().max() > 0, name
        error = triton_gradients.relative_error(b, a)
        assert error < rtol, (name, error)


def test_backward_is_the_triton_adjoint(params, monkeypatch):
    """No eager recomputation in the backward: with the eager loop and substep made to fail, a gradient still comes."""
    p = short(params, n_nodes=8, length=0.2)
    _, tri = sims(p, torch.float64)
    pos = crumpled(3, p, sigma=0.6, seed=7).to(DEVICE).requires_grad_(True)
    delta = torch.tensor([[0.03, 0.01], [-0.02, 0.04], [0.0, -0.05]], dtype=torch.float64, device=DEVICE)
    out = tri.move(pos, torch.tensor([0, 3, 7], device=DEVICE), delta)

    def fail(*args, **kwargs):
        raise AssertionError("the backward ran the eager path")
    monkeypatch.setattr(diffdlo.Simulator, "_move_eager", fail)
    monkeypatch.setattr(diffdlo.Simulator, "substep", fail)
    (grad,) = torch.autograd.grad((out ** 2).sum(), pos)
    assert torch.isfinite(grad).all() and grad.abs().max() > 0


def test_gradients_across_programs(params):
    """More ropes than one program holds: each program's scratch and each rope's slots are its own."""
    p = short(params, n_nodes=6, length=0.15)
    ref, tri = sims(p, torch.float64)
    batch = triton_kernel.BLOCK_ROPES + 3
    gen = torch.Generator().manual_seed(11)
    pos = crumpled(batch, p, sigma=0.7, seed=11).to(DEVICE)
    node = torch.randint(0, p.n_nodes, (batch,), generator=gen).to(DEVICE)
    delta = ((torch.rand(batch, 2, generator=gen, dtype=torch.float64) - 0.5) * 0.06).to(DEVICE)
    weights = torch.randn(batch, p.n_nodes, 2, generator=gen, dtype=torch.float64).to(DEVICE)
    grads = []
    for sim in (ref, tri):
        x = pos.clone().requires_grad_(True)
        d = delta.clone().requires_grad_(True)
        grads.append(torch.autograd.grad((sim.move(x, node, d) * weights).sum(), (x, d)))
    for a, b in zip(*grads):
        assert triton_gradients.relative_error(b, a) < 1e-9


def test_adjoint_memory_is_checkpointed_in_chunks(params):
    """About 2 sqrt(K) saved states per rope: checkpoints every chunk_substeps(K) substeps, only when a gradient is
    wanted."""
    assert [triton_kernel.chunk_substeps(k) for k in (1, 30, 64, 65, 101, 2001)] == [8, 8, 8, 16, 16, 64]
    p = short(params, n_nodes=8, length=0.2)
    pos = crumpled(3, p, sigma=0.6, seed=7).to(DEVICE)
    zeros = torch.zeros(3, dtype=torch.int64, device=DEVICE)
    phys = triton_kernel.columns(p, None, 3, DEVICE, torch.float64)
    args = (p, pos, torch.zeros_like(pos), zeros, torch.zeros(3, 2, dtype=torch.float64, device=DEVICE),
            torch.ones(3, dtype=torch.float64, device=DEVICE), zeros, phys)
    assert triton_kernel.forward(*args)[5] is None
    longest = p.max_drag_steps + p.settle_max_substeps + 1
    out_pos, out_vel, steps, _, _, ckpt, _ = triton_kernel.forward(*args, save=True)
    chunk = triton_kernel.chunk_substeps(longest)
    assert ckpt.shape == (3, longest // chunk + 2, 4, p.n_nodes)    # + the settle cap's release share
    assert torch.equal(ckpt[:, 0, 0], pos[..., 0]) and torch.equal(ckpt[:, 0, 1], pos[..., 1])
    # the checkpoint after substep `chunk` is the state a free evolution of `chunk` substeps reaches
    free = triton_kernel.forward(*args, fixed_steps=chunk)
    assert torch.equal(ckpt[:, 1, 0], free[0][..., 0]) and torch.equal(ckpt[:, 1, 3], free[1][..., 1])


@pytest.mark.parametrize("differentiable,every", [(False, 7), (True, 7), (True, 1)])
def test_frames_match_eager(params, differentiable, every):
    """Frames recorded in the kernel, per rope up to its own stop, equal the eager loop's; a loss on differentiable
    frames has the eager gradient (the adjoint adds each frame's gradient at its substep). Recording every substep,
    a rope stopped by the settle cap has a frame on its last substep, which is its returned (release-share) state."""
    p = short(params, n_nodes=6, length=0.15)
    ref, tri = sims(p, torch.float64)
    assert tri.engine == "triton" and "triton" not in tri.why_not
    pos = crumpled(3, p, sigma=0.5, seed=2).to(DEVICE)
    pos[2] = torch.stack([torch.linspace(-0.075, 0.075, p.n_nodes, dtype=torch.float64),
                          torch.zeros(p.n_nodes, dtype=torch.float64)], -1).to(DEVICE)     # at rest
    node = torch.tensor([0, 5, 2], device=DEVICE)
    delta = torch.tensor([[0.0213, 0.0041], [0.0, 0.0172], [0.0, 0.0]], dtype=torch.float64, device=DEVICE)
    weights = torch.randn(200, 3, p.n_nodes, 2, dtype=torch.float64,
                          generator=torch.Generator().manual_seed(4)).to(DEVICE)
    outputs = []
    for sim in (ref, tri):
        x = pos.clone().requires_grad_(True)
        d = delta.clone().requires_grad_(True)
        out, info = sim.move(x, node, d, return_info=True, record_every=every, differentiable_frames=differentiable)
        loss = (info.frames * weights[:len(info.frames)]).sum() + (out ** 2).sum()
        outputs.append((info, torch.autograd.grad(loss, (x, d))))
    (ia, ga), (ib, gb) = outputs
    steps = ib.substeps.tolist()
    assert steps[2] == p.settle_check_every and steps[0] > steps[2], steps     # ropes stop at different substeps
    assert every != 1 or not bool(ib.settled[0]), "rope 0 is to be stopped by the settle cap"
    assert ia.frames.shape == ib.frames.shape and (ia.frames - ib.frames).abs().max().item() < 1e-12
    assert ib.frames.requires_grad == differentiable
    for a, b in zip(ga, gb):
        assert (a - b).abs().max().item() < 1e-9 * a.abs().max().item(), (a, b)


def test_bad_inputs_name_the_problem(params):
    with pytest.raises(ValueError, match="kinematic"):
        diffdlo.Simulator(dataclasses.replace(params, controller="pid"), device=DEVICE, backend="triton")
    with pytest.raises(ValueError, match="backend must be one of"):
        diffdlo.Simulator(params, backend="trition")
    # CPU tensors without the interpreter: a clear error, checked in a fresh process (the env var is read there)
    code = ("import diffdlo\ntry:\n    diffdlo.Simulator(backend='triton')\nexcept RuntimeError as e:\n"
            "    print('ERR', e)\n")
    env = {**os.environ, "TRITON_INTERPRET": "0"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert "ERR backend 'triton' is unavailable on cpu" in out.stdout and "TRITON_INTERPRET=1" in out.stdout, out
    # without triton importable
    code = ("import sys\nsys.modules['triton'] = None\nimport diffdlo\n"
            "from diffdlo.planar.backends import triton_kernel\n"
            "assert not triton_kernel.available()\ntry:\n    diffdlo.Simulator(backend='triton')\n"
            "except RuntimeError as e:\n    print('ERR', e)\n"
            "print('AUTO', diffdlo.Simulator().backend, diffdlo.Simulator().engine == 'triton')\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert "ERR" in out.stdout and "triton is not importable" in out.stdout, out
    assert "AUTO auto False" in out.stdout, out


def test_auto_picks_triton_on_cuda_only(params):
    sim = diffdlo.Simulator(params, device=DEVICE)
    if DEVICE == "cuda":
        assert sim.engine == "triton" and sim.engine != "kernel"
    else:
        assert sim.engine != "triton" and "CUDA" in sim.why_not["triton"]


def test_every_kernel_compiles_for_a_gpu_without_one():
    """The compiled path, not the interpreter: each kernel variant, float32 and float64, compiled for sm_90 by Triton's
    own ptxas (no GPU needed) at the warps of WARPS, in a fresh process (the interpreter replaces the kernels)."""
    env = {**os.environ, "TRITON_INTERPRET": "0"}
    out = subprocess.run([sys.executable, "-m", "benchmarks.speed.triton_compile", "--arch", "90"], capture_output=True,
                         text=True, env=env, timeout=600, cwd=os.path.dirname(os.path.dirname(__file__)))
    assert out.returncode == 0, out.stderr[-3000:]
    rows = [line.split() for line in out.stdout.splitlines() if line.startswith(("move", "adjoint"))]
    assert len(rows) == 16, out.stdout
    for row in rows:
        registers = row[-2]
        assert registers.isdigit() and 0 < int(registers) <= 255, row


@pytest.mark.parametrize("max_settle", [60, 0])     # 0: the cap stops the rope on its release substep
def test_gradient_through_the_returned_state_equals_eager(params, max_settle):
    """A loss on the returned positions and velocities (which Simulator.move does not return): the adjoint of the
    release within the drag's last substep and of the settle cap's share equals autograd of the eager loop."""
    p = short(params, n_nodes=6, length=0.15, settle_max_substeps=max_settle)
    ref, tri = sims(p, torch.float64)
    pos = crumpled(5, p, sigma=0.6, seed=8).to(DEVICE)
    gen = torch.Generator().manual_seed(8)
    node = torch.randint(0, p.n_nodes, (5,), generator=gen).to(DEVICE)
    delta = ((torch.rand(5, 2, generator=gen, dtype=torch.float64) * 2 - 1) * 0.03).to(DEVICE)
    weights = torch.randn(2, *pos.shape, dtype=torch.float64, generator=gen).to(DEVICE)
    clipped = diffdlo.planar.control.clip_drag(delta, p.max_disp)
    steps = diffdlo.planar.control.path_substeps(clipped.norm(dim=-1), p)
    grads, capped = [], None
    for sim in (ref, tri):
        x, v, d = (t.clone().requires_grad_(True) for t in (pos, 0.01 * weights[1], clipped))
        if sim is ref:
            speed = diffdlo.planar.control.drag_speed(d.norm(dim=-1), p)
            out_x, out_v, _, _, settled, _ = sim._move_eager(x, v, node, d, speed, steps)
            capped = ~settled
        else:
            out_x, out_v, *_ = sim._triton_apply(x, v, node, d, steps, -1, None)
        loss = (out_x * weights[0]).sum() + (out_v * weights[1]).sum()
        grads.append(torch.autograd.grad(loss, (x, v, d)))
    assert int(capped.sum()) >= 3                                  # ropes stopped by the cap: their share applies
    for name, a, b in zip(("pos", "vel", "delta"), *grads):
        assert (a - b).abs().max().item() < 1e-9 * a.abs().max().item(), name


# ------------------------------------------------------------------ pegs and pins: the eager path
def test_pegs_and_pins_on_the_triton_engine_run_the_eager_path(params):
    p = triton_gradients.short_params(params)
    tri = diffdlo.Simulator(p, device=DEVICE, dtype=torch.float64, backend="triton")
    ref = diffdlo.Simulator(p, device=DEVICE, dtype=torch.float64, backend="torch")
    assert tri.engine == "triton" and tri.contact_engine == "torch"
    assert "eager" in tri.why_not["contact"] and "contact" not in ref.why_not
    pos = line(p).to(DEVICE)
    pegs = torch.tensor([[float(pos[0, 18, 0]), 0.016, 0.01]], dtype=torch.float64, device=DEVICE)   # over node 18
    node, delta = torch.tensor([19], device=DEVICE), torch.tensor([[0.0, 0.05]], dtype=torch.float64, device=DEVICE)
    pin = torch.tensor([17], device=DEVICE)
    torch.testing.assert_close(tri.move(pos, node, delta, pegs, pin), ref.move(pos, node, delta, pegs, pin),
                               rtol=0, atol=0)
    without = tri.move(pos, node, delta)                          # the Triton kernel itself, without contact
    assert float((without - ref.move(pos, node, delta, pegs, pin)).abs().max()) > 1e-3
