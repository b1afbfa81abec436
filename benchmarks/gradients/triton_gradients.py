"""The Triton adjoint's gradients against autograd through the eager loop, per input and dtype.

    TRITON_INTERPRET=1 python -m benchmarks.gradients.triton_gradients          (CPU, Triton's interpreter, ~1 min)
    python -m benchmarks.gradients.triton_gradients --device cuda               (the compiled kernels)
    TRITON_INTERPRET=1 python -m benchmarks.gradients.triton_gradients --full   (+ one full-length move, ~2 min more)

The problem is the tests' (tests/test_triton_kernel.py): seven ropes with short moves (drags of at most 40 substeps,
settle checked every 20 up to 60; max_speed 1 m/s so drags longer than 4 cm run faster), each stopping at its own
substep, through two chained moves and a free evolution of 25 substeps. For each input (start positions and
velocities, drag, k_s, k_b, k_d, mass) it prints the largest error over the largest entry, of the Triton gradient
against eager autograd in the same dtype, and of each against float64 eager autograd. ``--full`` adds one move
with the real params (params/cable.yaml: 20 nodes, up to 2,001 substeps, so the adjoint crosses some 30 of its
64-substep chunks) of two ropes in float64.
"""
from __future__ import annotations

import argparse
import dataclasses

import torch

import diffdlo

INPUTS = ("pos", "vel", "delta", "k_s", "k_b", "k_d", "mass")


def short_params(params, **changes):
    """A drag of at most 40 substeps, settle checked every 20 substeps up to 60: a straight rope at rest settles at
    the first check, a crumpled one runs to the cap."""
    changes = {"max_speed": 2.5, "max_drag_steps": 40, "settle_threshold": 2e-3, "settle_check_every": 20,
               "settle_max_substeps": 60, **changes}
    return dataclasses.replace(params, **changes)


def crumpled(batch: int, p, sigma: float, seed: int) -> torch.Tensor:
    """(B, N, 2) float64 ropes whose link directions are a random walk of step ``sigma`` (as tests/conftest.py's)."""
    return diffdlo.random_shape(batch, dataclasses.replace(p, sigma=sigma), torch.Generator().manual_seed(seed),
                                dtype=torch.float64)


def gradient_problem(p, dtype, device):
    """Seven ropes, each with its own stop: slow drags, a fast one (speed above max_speed), a clipped one, a zero drag
    (capped at settle_max_substeps), an end node, and a straight rope at rest that settles at the first check."""
    pos = crumpled(7, p, sigma=0.8, seed=3)
    pos[6] = torch.stack([torch.linspace(-0.25, 0.25, p.n_nodes, dtype=torch.float64),
                          torch.zeros(p.n_nodes, dtype=torch.float64)], -1)
    node = torch.tensor([0, 5, 19, 7, 12, 3, 2])
    # |delta| a whole number of substeps at max_speed is a kink (the path ends exactly on a substep), where float32
    # and float64 may take different one-sided derivatives: the drags here are away from it
    delta = torch.tensor([[0.0314, 0.0021], [0.0, -0.08], [0.3, 0.2], [0.0, 0.0], [0.004, 0.01], [0.02, 0.03],
                          [0.0, 0.0]], dtype=torch.float64)
    weights = torch.randn(2, 7, p.n_nodes, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    return [t.to(device, dtype) if t.is_floating_point() else t.to(device) for t in (pos, node, delta, weights)]


def chained_gradients(sim, pos, node, delta, weights):
    """Gradients of a loss on the final positions and velocities after two chained moves and a free evolution,
    w.r.t. the start positions and velocities, the drag and all four physical parameters; and the first move's
    MoveInfo."""
    p, batch = sim.params, pos.shape[0]
    x = pos.clone().requires_grad_(True)
    v = torch.zeros_like(pos).requires_grad_(True)
    d = delta.clone().requires_grad_(True)
    phys = diffdlo.Physics.of(p, batch, device=pos.device, dtype=pos.dtype, requires_grad=True)
    out, info = sim.move(x, node, d, vel=v, physics=phys, return_info=True)
    out = sim.move(out, (node + 1) % p.n_nodes, 0.6 * d, physics=phys)
    out, vel = sim.integrate(out, None, 25, physics=phys)
    loss = (out * weights[0]).sum() + (vel * weights[1]).sum()
    return info, torch.autograd.grad(loss, (x, v, d, phys.k_s, phys.k_b, phys.k_d, phys.mass))


def relative_error(a: torch.Tensor, b: torch.Tensor) -> float:
    """Largest |a - b| over the largest |b|."""
    return ((a.double() - b.double()).abs().max() / b.double().abs().max()).item()


def full_length(device) -> tuple[list[int], list[float]]:
    """One move of two ropes with the real params in float64 (a loss on the final positions): the substeps each
    took and the relative error of each Triton gradient against eager autograd."""
    p = diffdlo.load_params("cable")
    node = torch.tensor([3, 17], device=device)
    delta = torch.tensor([[0.0437, -0.0213], [-0.0712, 0.0555]], dtype=torch.float64, device=device)
    weights = torch.randn(1, 2, p.n_nodes, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    grads, steps = [], None
    for backend in ("torch", "triton"):
        sim = diffdlo.Simulator(p, device=device, dtype=torch.float64, backend=backend)
        pos = sim.random_shape(2, torch.Generator().manual_seed(5))
        x = pos.clone().requires_grad_(True)
        v = torch.zeros_like(pos).requires_grad_(True)
        d = delta.clone().requires_grad_(True)
        phys = diffdlo.Physics.of(p, 2, device=device, dtype=torch.float64, requires_grad=True)
        out, info = sim.move(x, node, d, vel=v, physics=phys, return_info=True)
        loss = (out * weights[0].to(device)).sum()
        grads.append(torch.autograd.grad(loss, (x, v, d, phys.k_s, phys.k_b, phys.k_d, phys.mass)))
        steps = info.substeps.tolist()
    return steps, [relative_error(b, a) for a, b in zip(*grads)]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cpu", help="cpu (needs TRITON_INTERPRET=1) or cuda")
    parser.add_argument("--full", action="store_true", help="also one move with the real params (~2 min more)")
    args = parser.parse_args(argv)
    from diffdlo.planar.backends import triton_kernel
    reason = triton_kernel.device_reason(torch.device(args.device))
    if reason is not None:
        parser.error(f"--device {args.device}: {reason}")
    p = short_params(diffdlo.load_params("cable"), max_speed=1.0)
    truth = None
    print(f"{'dtype':<8} {'path':<7} " + " ".join(f"{name:>9}" for name in INPUTS) + "   (vs float64 eager)")
    rows = {}
    for dtype in (torch.float64, torch.float32):
        problem = gradient_problem(p, dtype, args.device)
        for backend in ("torch", "triton"):
            sim = diffdlo.Simulator(p, device=args.device, dtype=dtype, backend=backend)
            rows[dtype, backend] = chained_gradients(sim, *problem)[1]
        truth = truth or rows[torch.float64, "torch"]
        for backend in ("torch", "triton"):
            errors = [relative_error(a, b) for a, b in zip(rows[dtype, backend], truth)]
            print(f"{str(dtype).removeprefix('torch.'):<8} {backend:<7} " + " ".join(f"{e:>9.1e}" for e in errors))
    print("Triton against eager autograd in the same dtype:")
    for dtype in (torch.float64, torch.float32):
        errors = [relative_error(a, b) for a, b in zip(rows[dtype, "triton"], rows[dtype, "torch"])]
        print(f"{str(dtype).removeprefix('torch.'):<8} {'triton':<7} " + " ".join(f"{e:>9.1e}" for e in errors))
    if args.full:
        steps, errors = full_length(args.device)
        print(f"Full-length move (params/cable.yaml, float64; substeps {steps}), Triton against eager autograd:")
        print(f"{'float64':<8} {'triton':<7} " + " ".join(f"{e:>9.1e}" for e in errors))


if __name__ == "__main__":
    main()
