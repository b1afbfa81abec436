"""The fused Triton kernel (backend "triton", diffdlo/triton_kernel.py) against the eager torch reference path.

Marked ``triton`` (kept out of the default run): ``TRITON_INTERPRET=1 python -m pytest -m triton`` runs the kernel in
Triton's CPU interpreter; on a machine with CUDA the same tests run the compiled kernel on the GPU. The interpreter
takes ~20-30 ms per substep, so the params are cut to ~100-substep moves.
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
from diffdlo import triton_kernel  # noqa: E402

pytestmark = pytest.mark.triton

DEVICE = "cuda" if torch.cuda.is_available() else "cpu"
if DEVICE == "cpu" and not triton_kernel.interpreting():
    pytestmark = [pytest.mark.triton,
                  pytest.mark.skip(reason="no CUDA device: run with TRITON_INTERPRET=1 to test in the interpreter")]


def short(params, **changes):
    """A drag of at most 40 substeps, settle checked every 20 substeps up to 60: a straight rope at rest settles at
    the first check, a crumpled one runs to the cap."""
    return dataclasses.replace(params, max_speed=2.5, max_drag_steps=40, settle_threshold=2e-3,
                               settle_check_every=20, settle_max_substeps=60, **changes)


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


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-6), (torch.float32, 1e-3)])
def test_move_matches_eager(params, dtype, tol):
    p = short(params)
    ref, tri = sims(p, dtype)
    assert tri.uses_triton() and not ref.uses_triton() and not tri.uses_kernel()
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
    clipped = diffdlo.control.clip_drag(delta, p.max_disp)
    steps = diffdlo.control.path_substeps(clipped.norm(dim=-1), p)
    _, vb, *_ = tri._triton_apply(pos, vel, node, clipped, steps, -1, None)
    speed = diffdlo.control.drag_speed(clipped.norm(dim=-1), p)
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
            assert (u - v).abs().max().item() < 1e-9


def test_gradients_match_eager(params):
    p = dataclasses.replace(short(params), n_nodes=8, length=0.2, settle_max_substeps=40)
    ref, tri = sims(p, torch.float64)
    pos = crumpled(3, p, sigma=0.6, seed=7).to(DEVICE)
    node = torch.tensor([0, 3, 7], device=DEVICE)
    delta = torch.tensor([[0.03, 0.01], [-0.02, 0.04], [0.0, -0.05]], dtype=torch.float64, device=DEVICE)
    k_s = torch.full((3,), 900.0, dtype=torch.float64, device=DEVICE)
    target = torch.randn(3, p.n_nodes, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(1)).to(DEVICE)
    grads = []
    for sim in (ref, tri):
        x = pos.clone().requires_grad_(True)
        d = delta.clone().requires_grad_(True)
        ks = k_s.clone().requires_grad_(True)
        phys = diffdlo.Physics(k_s=ks, k_b=p.k_b, k_d=p.k_d, mass=p.mass)
        out = sim.move(x, node, d, physics=phys)
        out2, vel = sim.integrate(out, None, 10)
        loss = ((out2 - target) ** 2).sum() + vel.sum()
        grads.append(torch.autograd.grad(loss, (x, d, ks)))
    for g_ref, g_tri in zip(*grads):
        assert torch.isfinite(g_tri).all()
        assert torch.allclose(g_ref, g_tri, rtol=1e-6, atol=1e-9), (g_ref, g_tri)


def test_frames_fall_back_to_eager(params):
    p = short(params, n_nodes=6, length=0.15)
    ref, tri = sims(p, torch.float64)
    pos = crumpled(2, p, sigma=0.5, seed=2).to(DEVICE)
    node = torch.tensor([0, 5], device=DEVICE)
    delta = torch.tensor([[0.02, 0.0], [0.0, 0.02]], dtype=torch.float64, device=DEVICE)
    assert "frames" in tri.triton_unsupported(record_every=10)
    a, ia = ref.move(pos, node, delta, return_info=True, record_every=10)
    b, ib = tri.move(pos, node, delta, return_info=True, record_every=10)
    assert torch.equal(a, b) and torch.equal(ia.frames, ib.frames)


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
    code = ("import sys\nsys.modules['triton'] = None\nimport diffdlo\nfrom diffdlo import triton_kernel\n"
            "assert not triton_kernel.available()\ntry:\n    diffdlo.Simulator(backend='triton')\n"
            "except RuntimeError as e:\n    print('ERR', e)\n"
            "print('AUTO', diffdlo.Simulator().backend, diffdlo.Simulator().uses_triton())\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert "ERR" in out.stdout and "triton is not importable" in out.stdout, out
    assert "AUTO auto False" in out.stdout, out


def test_auto_picks_triton_on_cuda_only(params):
    sim = diffdlo.Simulator(params, device=DEVICE)
    if DEVICE == "cuda":
        assert sim.uses_triton() and not sim.uses_kernel()
    else:
        assert not sim.uses_triton() and "CUDA" in sim.triton_unsupported()
