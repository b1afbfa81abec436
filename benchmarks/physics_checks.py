"""The cable model against the literature: elastica, modes, conservation and gradients (docs/SIMULATOR.md "The physics
against the literature"; tests/test_physics_literature.py asserts the same numbers).

- statics: the model's energy plus the load's potential minimised in float64 (Newton in link angles and stretches,
  exact autograd Hessian), the rope clamped by its first link: a pure end moment (a circular arc) and the
  large-deflection cantilever of Bisshopp & Drucker (1945) at alpha = P L^2 / EI of 1, 2 and 5, with the order of
  convergence in the number of nodes for two readings of the clamp;
- dynamics: the axial modes of a fixed-fixed chain and the first free-free bending modes of a rope on a frictionless
  table from the energy's Hessian and the mass matrix; momentum with the drag off, energy with it on, and the
  semi-implicit Euler's frequency error, through ``Simulator.integrate``;
- the departures of Table 2.1's cable from an elastic rod: the drag's damping ratios and relaxation times, the
  settle cap, the soft axial springs, k_b per node;
- the gradient of a shape loss w.r.t. the drags of H chained moves against central finite differences;
- pegs and the second gripper (benchmarks/contact_checks.py): contact forces, gradcheck, overlaps, a wrap,
  conservation, and the gradient's quality at the onset of contact (skip with --no-contact).

    python -m benchmarks.physics_checks                       # prints the markdown table (a few minutes)
    python -m benchmarks.physics_checks --out runs/physics    # also writes runs/physics/results.json
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from benchmarks import contact_checks
from diffdlo.utils.files import check_fresh_out
from diffdlo.planar.forces import energy, turning_angles
from diffdlo.planar.params import CableParams, load_params
from diffdlo.tasks.rewards import shape_error
from diffdlo.planar.rod import params_for_rod, rod_properties
from diffdlo.planar.simulator import Simulator

F64 = torch.float64
# Bisshopp & Drucker (1945), cantilever under a dead tip load perpendicular to the undeformed rod:
# alpha -> (tip deflection w/L, tip shortening u/L, tip angle [rad]), printed to 5 decimals.
BISSHOPP_DRUCKER = {1.0: (0.30172, 0.05643, 0.46135), 2.0: (0.49346, 0.16064, 0.78175),
                    5.0: (0.71379, 0.38763, 1.21537)}
# Free-free Euler-Bernoulli beam: beta_n L of the first two flexural modes (cos(bL) cosh(bL) = 1).
FREE_FREE_BETA_L = (4.730040744862704, 7.853204624095838)
NODES = (10, 20, 40, 80)
CLAMPS = ("midpoint", "node")
# The statics' axial stiffness relative to EI / L^2: the strain under the largest load is 5e-8, so the rod is
# inextensible far below the discretisation errors measured (Table 2.1's own, much softer, EA is a separate row).
STIFF_EA = 1e8


# ====================================================================== statics
def newton_minimise(total: Callable[[torch.Tensor], torch.Tensor], q: torch.Tensor, tol: float = 1e-20,
                    max_iter: int = 60) -> tuple[torch.Tensor, int, float]:
    """Minimise ``total`` from ``q`` by Newton's method with the exact autograd Hessian and a backtracking line
    search (a shifted Hessian where it is not positive definite). Stops when the Newton decrement g.H^-1.g is below
    ``tol`` (in the energy's units), or once below 1e-10 it stops falling tenfold per step: the floor rounding
    leaves with stiff axial springs (about 4e-17 at N = 80, an angle error of 1e-9 rad). Returns (q, iterations,
    last decrement)."""
    grad, hess = torch.func.grad(total), torch.func.hessian(total)
    dec = math.inf
    for it in range(max_iter):
        prev = dec
        g, h = grad(q), hess(q)
        chol, info = torch.linalg.cholesky_ex(h)
        if int(info) == 0:
            d = -torch.cholesky_solve(g[:, None], chol)[:, 0]
        else:
            shift = 2.0 * float(torch.linalg.eigvalsh(h)[0].abs())
            d = -torch.linalg.solve(h + shift * torch.eye(len(q), dtype=q.dtype), g)
        dec = float(-(d @ g))
        if dec < tol or (dec < 1e-10 and dec > 0.1 * prev):
            return q, it, dec
        e0, t = total(q), 1.0
        while float(total(q + t * d)) > float(e0) - 1e-4 * t * dec and t > 1e-10:
            t *= 0.5
        q = q + t * d
    raise RuntimeError(f"Newton did not converge in {max_iter} iterations (decrement {dec:.3g})")


@dataclasses.dataclass(frozen=True)
class ClampedRope:
    """A rope of n_nodes whose first link is held along +x: the rod a clamp reading makes of it.

    "midpoint": the rod runs from the clamp link's midpoint (the origin) to the last link's midpoint,
    L = (N - 2) l0: every interior node's bending spring stands for the l0 of rod around it (a midpoint rule), and
    the tip load acts at the last link's midpoint (half on each of its nodes).
    "node": the rod runs from the clamp node 0 (the origin) to node N - 1, L = (N - 1) l0, the load on node N - 1;
    the clamp link itself cannot bend, so the rod is l0 too stiff near the wall: O(1/N).
    """

    n_nodes: int
    clamp: str = "midpoint"
    EI: float = 1.0
    EA: float = STIFF_EA
    length: float = 1.0

    @property
    def rest_length(self) -> float:
        return self.length / (self.n_nodes - 2 if self.clamp == "midpoint" else self.n_nodes - 1)

    @property
    def k_b(self) -> float:
        return self.EI / self.rest_length

    @property
    def k_s(self) -> float:
        return self.EA / self.rest_length

    def positions(self, q: torch.Tensor) -> torch.Tensor:
        """(2 (N - 2),) link angles and stretches of links 1..N-2 -> (N, 2) node positions."""
        l0 = self.rest_length
        x0 = -l0 / 2 if self.clamp == "midpoint" else 0.0
        fixed = torch.tensor([[x0, 0.0], [x0 + l0, 0.0]], dtype=q.dtype)
        angle, stretch = q.view(2, -1)
        e = l0 * (1 + stretch)[:, None] * torch.stack([angle.cos(), angle.sin()], -1)
        return torch.cat([fixed, fixed[1] + e.cumsum(0)], 0)

    def tip(self, pos: torch.Tensor) -> torch.Tensor:
        return 0.5 * (pos[-1] + pos[-2]) if self.clamp == "midpoint" else pos[-1]

    def model_energy(self, pos: torch.Tensor) -> torch.Tensor:
        return energy(pos[None], self.rest_length, self.k_s, self.k_b)[0]

    def straight(self) -> torch.Tensor:
        return torch.zeros(2 * (self.n_nodes - 2), dtype=F64)


def cantilever(n_nodes: int, alphas=(1.0, 2.0, 5.0), clamp: str = "midpoint", EA: float = STIFF_EA) -> dict:
    """The clamped rope under a dead tip load P = alpha EI / L^2 along -y, loaded in whole steps of alpha (each
    equilibrium the next one's start). Returns alpha -> {w, u, angle (tip, over L and in rad), decrement,
    iterations}."""
    rope = ClampedRope(n_nodes, clamp, EA=EA)
    q, out, done = rope.straight(), {}, 0.0
    for alpha in alphas:
        for a in np.linspace(done, alpha, max(1, math.ceil(alpha - done)) + 1)[1:]:
            load = float(a) * rope.EI / rope.length ** 2

            def total(q, load=load):
                pos = rope.positions(q)
                return rope.model_energy(pos) + load * rope.tip(pos)[1]
            q, iterations, dec = newton_minimise(total, q)
        done = alpha
        pos = rope.positions(q)
        tip, e = rope.tip(pos), pos[-1] - pos[-2]
        out[alpha] = {"w": -float(tip[1]) / rope.length, "u": 1.0 - float(tip[0]) / rope.length,
                      "angle": -math.atan2(float(e[1]), float(e[0])), "decrement": dec, "iterations": iterations}
    return out


def elastica_reference(alpha: float) -> tuple[float, float, float]:
    """The inextensible elastica EI theta'' = -P cos(theta), theta(0) = 0, theta'(L) = 0, solved by shooting
    (scipy, rtol 1e-12): (w/L, u/L, tip angle). Checks the printed table's digits independently."""
    from scipy.integrate import solve_ivp
    from scipy.optimize import brentq

    def run(k0):
        def rhs(s, y):
            return [y[1], -alpha * math.cos(y[0]), math.cos(y[0]), math.sin(y[0])]
        return solve_ivp(rhs, (0.0, 1.0), [0.0, k0, 0.0, 0.0], rtol=1e-12, atol=1e-14).y[:, -1]
    k0 = brentq(lambda k: run(k)[1], 0.0, alpha, xtol=1e-14)
    theta, _, x, y = run(k0)
    return y, 1.0 - x, theta


def end_moment(n_nodes: int, turn: float = math.pi / 2) -> dict:
    """The clamped rope ("midpoint" reading) under an end couple M = turn EI / L on its last link (potential
    -M x the last link's angle, from the positions). The model's exact solution: every turning angle M / k_b,
    a regular polygon whose link midpoints lie on a circle of radius l0 / (2 tan(beta / 2)) touching the clamp
    link at the origin. Returns the solver's departures from it and the polygon's from the continuous arc."""
    rope = ClampedRope(n_nodes, "midpoint", EA=1.0e3)
    moment = turn * rope.EI / rope.length

    def total(q):
        pos = rope.positions(q)
        e = pos[-1] - pos[-2]
        return rope.model_energy(pos) - moment * torch.atan2(e[1], e[0])
    q, _, dec = newton_minimise(total, rope.straight(), tol=1e-24)
    pos = rope.positions(q)
    beta = turning_angles(pos[None])[0]
    b = moment / rope.k_b
    r = rope.rest_length / (2 * math.tan(b / 2))
    theta = (n_nodes - 2) * b
    polygon_tip = torch.tensor([r * math.sin(theta), r * (1 - math.cos(theta))], dtype=F64)
    radius = rope.EI / moment
    arc_tip = torch.tensor([radius * math.sin(theta), radius * (1 - math.cos(theta))], dtype=F64)
    tip = rope.tip(pos)
    return {"beta_spread": float((beta - b).abs().max()), "beta": b,
            "tip_vs_polygon": float((tip - polygon_tip).norm()) / rope.length,
            "link_strain": float(((pos[1:] - pos[:-1]).norm(dim=-1) / rope.rest_length - 1).abs().max()),
            "tip_vs_arc": float((tip - arc_tip).norm()) / rope.length,
            "tip_vs_arc_predicted": float(arc_tip.norm()) * (1 - b / (2 * math.tan(b / 2))) / rope.length,
            "decrement": dec}


def order(errors: dict[int, float]) -> float:
    """Least-squares slope of -log(error) against log(N): the convergence order."""
    n = np.log(np.array(list(errors), dtype=float))
    e = np.log(np.abs(np.array(list(errors.values()), dtype=float)))
    return float(-np.polyfit(n, e, 1)[0])


# ====================================================================== modes
def rest_hessian(p: CableParams) -> torch.Tensor:
    """(2N, 2N) Hessian of the model's energy about the straight rope along x at rest, dofs (x_0, y_0, x_1, ...)."""
    n, l0 = p.n_nodes, p.rest_length
    rest = torch.stack([l0 * torch.arange(n, dtype=F64), torch.zeros(n, dtype=F64)], -1).flatten()
    return torch.func.hessian(lambda q: energy(q.view(1, n, 2), l0, p.k_s, p.k_b)[0])(rest)


def axial_modes_fixed_fixed(p: CableParams) -> dict:
    """Both end nodes fixed: the interior nodes' x-block of the Hessian over the node mass, against the chain's
    exact omega_j = 2 sqrt(k_s / m) sin(j pi / (2 n + 2)) for n = N - 2 free masses."""
    hess = rest_hessian(p)
    idx = torch.arange(1, p.n_nodes - 1) * 2
    omega = torch.linalg.eigvalsh(hess[idx][:, idx] / p.node_mass).clamp_min(0).sqrt()
    n = p.n_nodes - 2
    j = torch.arange(1, n + 1, dtype=F64)
    exact = 2 * math.sqrt(p.k_s / p.node_mass) * torch.sin(j * math.pi / (2 * n + 2))
    return {"max_rel_error": float(((omega - exact) / exact).abs().max()), "omega_1": float(omega[0]),
            "omega_max": float(omega[-1])}


def bending_modes_free_free(p: CableParams, lumped: str = "model") -> dict:
    """The first two flexural modes of the free rope on a frictionless table: the y-block of the Hessian about the
    straight rope (axial and transverse motion decouple there) with the mass matrix, the two rigid-body modes
    (translation, rotation) dropped, against (beta_n L)^2 sqrt(EI / (mu L^4)) for the rod of ``rod_properties``.
    ``lumped``: "model" (mass / N on every node, as the simulator) or "rod" (a rod's lumping, half at the ends)."""
    hess = rest_hessian(p)
    idx = torch.arange(p.n_nodes) * 2 + 1
    rod = rod_properties(p)
    mass = torch.full((p.n_nodes,), p.node_mass, dtype=F64)
    if lumped == "rod":
        mass = torch.full((p.n_nodes,), rod.mass_per_length * rod.rest_length, dtype=F64)
        mass[[0, -1]] /= 2
    inv_sqrt = mass.rsqrt()
    k = hess[idx][:, idx] * inv_sqrt[:, None] * inv_sqrt[None, :]
    omega2 = torch.linalg.eigvalsh(k)
    omega = omega2[2:4].clamp_min(0).sqrt()
    scale = math.sqrt(rod.EI / (rod.mass_per_length * rod.length ** 4))
    exact = torch.tensor([b ** 2 * scale for b in FREE_FREE_BETA_L], dtype=F64)
    return {"omega": omega.tolist(), "exact": exact.tolist(), "rel_error": ((omega - exact) / exact).tolist(),
            "rigid_omega2": [float(x) for x in omega2[:2]]}


# ====================================================================== through the simulator
def free_ropes(p: CableParams, batch: int = 4, speed: float = 0.05, seed: int = 0) -> tuple[torch.Tensor, ...]:
    """Random rope shapes (the thesis's sigma) with random node velocities [m/s], float64."""
    sim = Simulator(p, dtype=F64)
    g = torch.Generator().manual_seed(seed)
    pos = sim.random_shape(batch, generator=g)
    vel = speed * torch.randn(pos.shape, generator=g, dtype=F64)
    return sim, pos, vel


def momentum_undamped(p: CableParams, substeps: int = 1000) -> dict:
    """Drag off (k_d = 0): total momentum over ``substeps`` of free evolution (no grasp), and the energy's relative
    spread (semi-implicit Euler is symplectic: bounded, not exact)."""
    sim, pos, vel = free_ropes(dataclasses.replace(p, k_d=0.0))
    m = p.node_mass
    p0 = m * vel.sum(1)
    e0 = sim.energy(pos) + 0.5 * m * (vel ** 2).sum((1, 2))
    energies = []
    x, v = pos, vel
    for _ in range(10):
        x, v = sim.integrate(x, v, substeps // 10)
        energies.append(sim.energy(x) + 0.5 * m * (v ** 2).sum((1, 2)))
    drift = float((m * v.sum(1) - p0).norm(dim=-1).max() / p0.norm(dim=-1).max())
    spread = float((torch.stack(energies) - e0).abs().amax(0).max() / e0.min())
    return {"momentum_rel_change": drift, "energy_rel_spread": spread, "substeps": substeps}


def energy_damped(p: CableParams, substeps: int = 300) -> dict:
    """Drag on: kinetic + potential energy after every substep of free evolution; its largest rise over one
    substep relative to the start energy (0 for a dissipative integrator) and the fraction left at the end."""
    sim, pos, vel = free_ropes(p, speed=0.2)
    m = p.node_mass
    total = [sim.energy(pos) + 0.5 * m * (vel ** 2).sum((1, 2))]
    x, v = pos, vel
    for _ in range(substeps):
        x, v = sim.integrate(x, v, 1)
        total.append(sim.energy(x) + 0.5 * m * (v ** 2).sum((1, 2)))
    total = torch.stack(total)
    rise = float(((total[1:] - total[:-1]) / total[0]).max())
    return {"max_rise": rise, "left": float((total[-1] / total[0]).max()), "substeps": substeps}


def integrator_frequency(p: CableParams, mode: int | None = None, substeps: int = 400) -> dict:
    """Free-free axial mode ``mode`` (default the stiffest, N - 1) of the undamped straight rope, started from a
    0.1 % displacement in its shape and run through ``Simulator.integrate``: its frequency from the recurrence
    a_{k+1} + a_{k-1} = 2 cos(omega dt) a_k, against the model's omega_j = 2 sqrt(k_s / m) sin(j pi / (2 N)) and
    the semi-implicit Euler's own prediction (2 / dt) asin(omega dt / 2)."""
    q = dataclasses.replace(p, k_d=0.0)
    n, l0, dt = q.n_nodes, q.rest_length, q.dt
    mode = n - 1 if mode is None else mode
    sim = Simulator(q, dtype=F64)
    shape = torch.cos(mode * math.pi * (torch.arange(n, dtype=F64) + 0.5) / n)
    rest = torch.stack([l0 * torch.arange(n, dtype=F64), torch.zeros(n, dtype=F64)], -1)[None]
    x = rest.clone()
    x[0, :, 0] += 1e-3 * l0 * shape
    v = torch.zeros_like(x)
    amp = []
    for _ in range(substeps):
        x, v = sim.integrate(x, v, 1)
        amp.append(float(((x[0, :, 0] - rest[0, :, 0]) * shape).sum()))
    a = np.array(amp)
    c = float(np.dot(a[2:] + a[:-2], a[1:-1]) / (2 * np.dot(a[1:-1], a[1:-1])))
    measured = math.acos(c) / dt
    exact = 2 * math.sqrt(q.k_s / q.node_mass) * math.sin(mode * math.pi / (2 * n))
    predicted = 2 / dt * math.asin(exact * dt / 2)
    return {"mode": mode, "omega": exact, "measured": measured, "vs_prediction": measured / predicted - 1,
            "vs_model": measured / exact - 1}


def settle_cap(p: CableParams) -> dict:
    """A rope released as a half circle (turning angles pi / (N - 2)) settled by ``Simulator.settle``: the elastic
    rod's (and the model's) equilibrium is straight, so what bending energy the cap leaves says how far from
    equilibrium a settled rope is."""
    sim = Simulator(p, dtype=F64)
    n = p.n_nodes
    beta = math.pi / (n - 2)
    angle = beta * torch.arange(n - 1, dtype=F64)
    links = p.rest_length * torch.stack([angle.cos(), angle.sin()], -1)
    pos = torch.cat([torch.zeros(1, 2, dtype=F64), links.cumsum(0)])[None]
    out, info = sim.settle(pos, return_info=True)
    e0, e1 = float(sim.energy(pos)[0]), float(sim.energy(out)[0])
    chord0 = float((pos[0, -1] - pos[0, 0]).norm())
    chord1 = float((out[0, -1] - out[0, 0]).norm())
    return {"energy_left": e1 / e0, "chord_before": chord0 / p.length, "chord_after": chord1 / p.length,
            "substeps": int(info.substeps[0]), "settled": bool(info.settled[0])}


def drag_departure(p: CableParams) -> dict:
    """The table's viscous drag k_d on each node against the undamped elastic rod: damping ratios
    zeta = k_d / (2 m omega) of the first bending and axial modes, and the overdamped relaxation time
    k_d / (m omega^2) of the first bending mode (a free rope's slowest straightening)."""
    bend = bending_modes_free_free(p)["omega"][0]
    axial = axial_modes_fixed_fixed(p)["omega_1"]
    m = p.node_mass
    return {"zeta_bending_1": p.k_d / (2 * m * bend), "zeta_axial_1": p.k_d / (2 * m * axial),
            "bending_relaxation_s": p.k_d / (m * bend ** 2), "omega_bending_1": bend}


# ====================================================================== gradients
def gradient_horizon(p: CableParams, horizon: int, directions: int = 16, step: float = 1e-6, seed: int = 0) -> dict:
    """The gradient of shape_error(final rope, straight target) w.r.t. the drags (H, 2) of ``horizon`` chained
    ``Simulator.move`` calls against central finite differences along random unit directions, in float64. The
    FD runs go in one batch (rope 0 the centre, then +h and -h per direction). A direction whose +h and -h runs
    differ in any move's substep count or settled flag crossed a discrete decision (a drag's whole number of
    substeps, the settle check): the loss jumps there, which the gradient by construction ignores, so those are
    counted and left out of the error. The step: 1e-6 m balances the FD's truncation (h^2) against rounding
    (1e-16 / h) best (measured 1e-5 to 1e-8); at 1e-5 some directions cross a substep boundary (the path is cut in
    steps of max_speed dt = 1e-4 m) at H >= 20."""
    sim = Simulator(p, dtype=F64)
    g = torch.Generator().manual_seed(seed)
    start = sim.random_shape(1, generator=g)
    nodes = torch.randint(p.n_nodes, (horizon,), generator=g)
    drags = (torch.rand(horizon, 2, generator=g, dtype=F64) * 2 - 1) * 0.05
    target = sim.target_shape("horizontal")
    u = torch.randn(directions, horizon, 2, generator=g, dtype=F64)
    u = u / u.flatten(1).norm(dim=1)[:, None, None]

    def rollout(d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        pos, steps = start.expand(d.shape[0], -1, -1).contiguous(), []
        for k in range(horizon):
            pos, info = sim.move(pos, nodes[k].repeat(d.shape[0]), d[:, k], return_info=True)
            steps.append(info.substeps * 2 + info.settled.long())
        return shape_error(pos, target), torch.stack(steps, 1)

    d0 = drags.clone().requires_grad_()
    t0 = time.perf_counter()
    loss, _ = rollout(d0[None])
    (grad,) = torch.autograd.grad(loss.sum(), d0)
    t_grad = time.perf_counter() - t0
    with torch.no_grad():
        batch = torch.cat([drags[None] + step * u, drags[None] - step * u])
        losses, steps = rollout(batch)
    fd = (losses[:directions] - losses[directions:]) / (2 * step)
    ad = (grad[None] * u).flatten(1).sum(1)
    clean = (steps[:directions] == steps[directions:]).all(1)
    rel_all = (ad - fd).abs() / fd.abs().clamp_min(1e-30)
    rel = rel_all[clean]
    return {"horizon": horizon, "loss": float(loss[0].detach()), "rel_error_all_max": float(rel_all.max()),
            "grad_norm": float(grad.norm()),
            "grad_norm_first": float(grad[0].norm()), "grad_norm_last": float(grad[-1].norm()),
            "rel_error_max": float(rel.max()) if rel.numel() else float("nan"),
            "rel_error_median": float(rel.median()) if rel.numel() else float("nan"),
            "directions": directions, "crossed": int((~clean).sum()), "step": step, "grad_seconds": t_grad}


def substep_boundary_jump(p: CableParams, length: float = 0.03, gap: float = 1e-11) -> dict:
    """How far the settled rope moves [m] when a drag of ``length`` (a whole number of max_speed dt steps) grows by
    2 ``gap``: the path then takes one substep more. Before the release within the last substep
    (control.last_substep_fraction) this was 36 um: just short of the boundary the node was released at max_speed,
    just past it after a last substep of almost nothing, so at rest, and the settle cap, counted from the release,
    ended a substep later."""
    sim = Simulator(p, dtype=F64)
    start = sim.random_shape(1, generator=torch.Generator().manual_seed(0)).expand(2, -1, -1).contiguous()
    d = torch.tensor([[length - gap, 0.0], [length + gap, 0.0]], dtype=F64)
    out, info = sim.move(start, torch.full((2,), 3), d, return_info=True)
    return {"jump": float((out[1] - out[0]).norm(dim=-1).max()), "drag_substeps": info.drag_substeps.tolist(),
            "gap": 2 * gap}


def gradient_params(n_nodes: int = 10) -> CableParams:
    """Table 2.1's cable with fewer nodes (the gradient table's rope)."""
    return dataclasses.replace(load_params("cable"), n_nodes=n_nodes)


# ====================================================================== the table
def run_all(nodes=NODES, horizons=(1, 5, 20, 50), contact: bool = True) -> dict:
    p = load_params("cable")
    res: dict = {"bisshopp_drucker": {str(a): v for a, v in BISSHOPP_DRUCKER.items()}}
    res["elastica_ode"] = {str(a): elastica_reference(a) for a in BISSHOPP_DRUCKER}
    res["cantilever"] = {c: {n: cantilever(n, clamp=c) for n in nodes} for c in CLAMPS}
    rod = rod_properties(p)
    soft = rod.EA * (1.0 / rod.length) ** 2 / rod.EI          # Table 2.1's EA / (EI / L^2), in the unit rod
    res["cantilever_table21_EA"] = cantilever(20, clamp="midpoint", EA=soft)
    res["end_moment"] = {n: end_moment(n) for n in nodes}
    res["axial_fixed_fixed"] = {n: axial_modes_fixed_fixed(dataclasses.replace(p, n_nodes=n)) for n in nodes}
    res["bending_free_free"] = {n: bending_modes_free_free(params_for_rod(rod.EI, rod.EA, rod.mass_per_length,
                                                                          rod.length, n, p)) for n in nodes}
    res["bending_free_free_rod_lumped"] = {
        n: bending_modes_free_free(params_for_rod(rod.EI, rod.EA, rod.mass_per_length, rod.length, n, p), "rod")
        for n in nodes}
    res["momentum_undamped"] = momentum_undamped(p)
    res["energy_damped"] = energy_damped(p)
    res["integrator_stiffest"] = integrator_frequency(p)
    res["integrator_slowest"] = integrator_frequency(p, mode=1, substeps=2000)
    res["settle_cap"] = settle_cap(p)
    res["drag"] = drag_departure(p)
    res["rod_table21"] = dataclasses.asdict(rod)
    res["rod_table21"]["n40_same_k_b_EI"] = rod_properties(dataclasses.replace(p, n_nodes=40)).EI
    res["gradients"] = [gradient_horizon(gradient_params(), h) for h in horizons]
    res["gradients_step_1e-5"] = [gradient_horizon(gradient_params(), h, step=1e-5) for h in horizons if h >= 20]
    res["substep_boundary_jump"] = substep_boundary_jump(gradient_params())
    if contact:
        res["contact"] = contact_checks.run_all(p)
    return res


def _cmd(extra: str = "") -> str:
    return f"`python -m benchmarks.physics_checks{extra}`"


def table(res: dict) -> str:
    """The markdown docs/SIMULATOR.md quotes."""
    nodes = list(res["end_moment"])
    rows = ["| check | literature / exact | measured | command |", "|---|---|---|---|"]
    cmd = _cmd()
    for a, (w, u, th) in ((float(k), v) for k, v in res["bisshopp_drucker"].items()):
        ode = res["elastica_ode"][str(a)]
        for c in CLAMPS:
            got = res["cantilever"][c][nodes[-1]][a]
            rows.append(f"| cantilever alpha={a:g}, clamp {c}, N={nodes[-1]}: w/L, u/L, tip angle | "
                        f"{w:.5f}, {u:.5f}, {th:.5f} (Bisshopp & Drucker 1945; ODE {ode[0]:.6f}, {ode[1]:.6f}, "
                        f"{ode[2]:.6f}) | {got['w']:.5f}, {got['u']:.5f}, {got['angle']:.5f} "
                        f"(errors {got['w'] - ode[0]:+.1e}, {got['u'] - ode[1]:+.1e}, {got['angle'] - ode[2]:+.1e}) "
                        f"| {cmd} |")
    for c in CLAMPS:
        for a in (1.0, 5.0):
            ode = res["elastica_ode"][str(a)][0]
            errs = {n: res["cantilever"][c][n][a]["w"] - ode for n in nodes}
            rows.append(f"| cantilever alpha={a:g}, clamp {c}: w/L error at N = {', '.join(map(str, nodes))} | "
                        f"-> 0 | {', '.join(f'{e:+.2e}' for e in errs.values())}: order {order(errs):.2f} (in N - 2: "
                        f"{order({n - 2: e for n, e in errs.items()}):.2f}) | {cmd} |")
    soft, stiff = res["cantilever_table21_EA"][5.0], res["cantilever"]["midpoint"][20][5.0]
    rod = res["rod_table21"]
    rows.append(f"| departure: Table 2.1's EA (EA L^2/EI = {rod['EA'] / rod['EI'] * rod['length'] ** 2:.3g}), "
                f"cantilever alpha=5, N=20 | inextensible | w/L {soft['w'] - stiff['w']:+.1e}, u/L "
                f"{soft['u'] - stiff['u']:+.1e} from the inextensible rope | {cmd} |")
    em = res["end_moment"]
    rows.append(f"| end moment (turn pi/2): turning angles all M/k_b, tip on the polygon's circle | exact | "
                f"max |beta - M/k_b| {max(v['beta_spread'] for v in em.values()):.1e} rad, tip "
                f"{max(v['tip_vs_polygon'] for v in em.values()):.1e} L, strain "
                f"{max(v['link_strain'] for v in em.values()):.1e} | {cmd} |")
    arc = {n: v["tip_vs_arc"] for n, v in em.items()}
    predicted = [v["tip_vs_arc_predicted"] for v in em.values()]
    rows.append(f"| end moment: tip vs the continuous arc at N = {', '.join(map(str, nodes))} | "
                f"predicted (1 - beta/(2 tan(beta/2))) {', '.join(f'{v:.2e}' for v in predicted)} L | "
                f"{', '.join(f'{v:.2e}' for v in arc.values())} L: order {order(arc):.2f} (in N - 2: "
                f"{order({n - 2: e for n, e in arc.items()}):.2f}) | {cmd} |")
    ax = res["axial_fixed_fixed"]
    rows.append(f"| axial modes, fixed-fixed, N = {', '.join(map(str, nodes))} | 2 sqrt(k/m) sin(j pi/(2n+2)) | "
                f"max rel. error {max(v['max_rel_error'] for v in ax.values()):.1e} | {cmd} |")
    for key, label in (("bending_free_free", "masses mass/N (the model)"),
                       ("bending_free_free_rod_lumped", "rod-lumped masses (ends half)")):
        bm = res[key]
        for j in range(2):
            errs = {n: v["rel_error"][j] for n, v in bm.items()}
            rows.append(f"| free-free bending mode {j + 1}, {label}, Table 2.1's rod, N = "
                        f"{', '.join(map(str, nodes))} | (beta L)^2 = {FREE_FREE_BETA_L[j] ** 2:.4f}: omega "
                        f"{bm[nodes[0]]['exact'][j]:.4f} rad/s | rel. error "
                        f"{', '.join(f'{e:+.2e}' for e in errs.values())}: order {order(errs):.2f} | {cmd} |")
    mo = res["momentum_undamped"]
    rows.append(f"| k_d = 0, {mo['substeps']} free substeps: momentum; energy | conserved | "
                f"momentum rel. change {mo['momentum_rel_change']:.1e}; energy spread {mo['energy_rel_spread']:.1e} "
                f"(symplectic, bounded) | {cmd} |")
    ed = res["energy_damped"]
    rows.append(f"| k_d = 100: kinetic + potential over {ed['substeps']} substeps | non-increasing | "
                f"largest rise per substep {ed['max_rise']:+.1e} of E0; {ed['left']:.2e} of E0 left | {cmd} |")
    for key in ("integrator_slowest", "integrator_stiffest"):
        it = res[key]
        rows.append(f"| departure: semi-implicit Euler, free-free axial mode {it['mode']} (omega "
                    f"{it['omega']:.1f} rad/s, dt {1e-3:g} s) | omega | frequency {it['vs_model']:+.2e} relative "
                    f"(vs the scheme's own (2/dt) asin(omega dt/2): {it['vs_prediction']:+.1e}) | {cmd} |")
    dr = res["drag"]
    rows.append(f"| departure: the drag k_d | undamped rod | damping ratio {dr['zeta_bending_1']:.0f} (bending 1), "
                f"{dr['zeta_axial_1']:.0f} (axial 1): no vibration; first bending mode relaxes in "
                f"{dr['bending_relaxation_s']:.0f} s | {cmd} |")
    sc = res["settle_cap"]
    rows.append(f"| departure: the settle cap, half-circle rope released | straight (energy 0) | after "
                f"{sc['substeps']} substeps (settled: {sc['settled']}): {sc['energy_left']:.4f} of the bending energy "
                f"left, end-to-end {sc['chord_before']:.3f} L -> {sc['chord_after']:.3f} L | {cmd} |")
    rows.append(f"| Table 2.1 as a rod | EI = k_b l0, EA = k_s l0 | EI {rod['EI']:.3e} N m^2, EA {rod['EA']:.3g} N, "
                f"mu {rod['mass_per_length']:.3g} kg/m, drag {rod['drag_per_length']:.3g} N s/m^2; the same k_b at "
                f"N=40: EI {rod['n40_same_k_b_EI']:.3e} | `diffdlo.planar.rod.rod_properties(load_params('cable'))` |")
    rows += ["", "| moves H | loss [m] | gradient norm (first / last drag) | rel. error vs central FD (median / max, "
             "clean directions) | directions crossing a discrete decision | gradient s |", "|---|---|---|---|---|---|"]
    for gr in res["gradients"]:
        rows.append(f"| {gr['horizon']} | {gr['loss']:.4f} | {gr['grad_norm']:.3g} ({gr['grad_norm_first']:.3g} / "
                    f"{gr['grad_norm_last']:.3g}) | {gr['rel_error_median']:.1e} / {gr['rel_error_max']:.1e} | "
                    f"{gr['crossed']} of {gr['directions']} | {gr['grad_seconds']:.2f} |")
    for gr in res.get("gradients_step_1e-5", []):
        rows.append(f"| {gr['horizon']}, FD step 1e-5 m | | | all directions: max {gr['rel_error_all_max']:.1e} | "
                    f"{gr['crossed']} of {gr['directions']} | |")
    jump = res["substep_boundary_jump"]
    rows += ["", f"Continuity: a drag crossing a whole number of substeps ({jump['drag_substeps']}) by "
             f"{jump['gap']:.0e} m moves the settled rope by {jump['jump']:.1e} m ({cmd}; 3.6e-05 m before the "
             f"release within the last substep)."]
    if "contact" in res:
        rows += ["", "Pegs and the second gripper:", "", "| check | expected | measured | command |",
                 "|---|---|---|---|"] + contact_checks.rows(res["contact"], cmd)
    return "\n".join(rows)


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    return x


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.physics_checks", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, help="folder for results.json")
    ap.add_argument("--overwrite", action="store_true", help="replace an existing results.json in --out")
    ap.add_argument("--nodes", type=int, nargs="+", default=list(NODES))
    ap.add_argument("--horizons", type=int, nargs="+", default=[1, 5, 20, 50])
    ap.add_argument("--no-contact", action="store_true", help="skip the pegs' checks (benchmarks/contact_checks.py)")
    args = ap.parse_args(argv)
    if args.out is not None:
        try:
            check_fresh_out(args.out, args.overwrite, "physics checks")
        except FileExistsError as exc:
            print(exc, file=sys.stderr)
            return 2
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    res = run_all(tuple(args.nodes), tuple(args.horizons), contact=not args.no_contact)
    res["seconds"] = time.perf_counter() - t0
    print(table(res))
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "results.json").write_text(json.dumps(_jsonable(res), indent=2))
        print(f"wrote {args.out / 'results.json'}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
