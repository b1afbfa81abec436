"""Fit the cable's physical parameters to recorded moves by gradient descent through the simulator, and say what the
data can identify.

The recorded moves are independent given their start shapes (each starts from the rope at rest), so every move of a
recording and every start of the fit is simulated in ONE batched ``Simulator.move`` with per-rope parameters
(``diffdlo.Physics``): candidate s of S, move m of M is rope s * M + m. The parameters are fitted in log space
relative to nominal ones, theta = log(value / nominal), bounded to ``bound`` (default |theta| <= log 4), with Adam on
the mean squared node-position error over the visible recorded frames.

Scaling all four parameters by one factor leaves every trajectory exactly as it is (forces and masses scale
together), so absolute values are never identifiable from positions, only ratios.

Identifiability: in this overdamped regime (inertia time ~0.1 ms against moves of ~1 s) the trajectories depend on
the ratios of the stiffnesses to the damping, k_s/k_d and k_b/k_d, and hardly on the mass; settled shapes alone
would only give k_b/k_s. ``identifiability`` measures it from the data: the Gauss-Newton curvature J^T J of the
residuals in theta (J by central differences), its eigenvalues, and for each named combination (a direction in
theta) its standard deviation sigma sqrt(c^T (J^T J)^+ c), sigma estimated from the fit's residual. A combination is
identifiable when its standard deviation is below ``identifiable_std`` (default 0.05: 5 %).
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any

import torch

from .physics import PHYSICAL, Physics
from .simulator import Simulator

# Named combinations of log parameters (log k_s, log k_b, log k_d, log mass) reported by identifiability.
COMBINATIONS = {"k_s/k_d": (1, 0, -1, 0), "k_b/k_d": (0, 1, -1, 0), "k_b/k_s": (-1, 1, 0, 0), "mass/k_d": (0, 0, -1, 1),
                "k_s": (1, 0, 0, 0), "k_b": (0, 1, 0, 0), "k_d": (0, 0, 1, 0), "mass": (0, 0, 0, 1)}


@dataclasses.dataclass
class Moves:
    """Recorded moves, batched: ``start`` (M, N, 2) the rope at rest before each move, ``node`` (M,), ``delta``
    (M, 2) [m], ``frames`` (M, F, N, 2) the rope every ``record_every`` substeps from the move's start (frame 0 is
    the start; NaN where not recorded), ``visible`` (M, F, N) bool (False where not recorded or tracking was lost)."""
    start: torch.Tensor
    node: torch.Tensor
    delta: torch.Tensor
    frames: torch.Tensor
    visible: torch.Tensor
    record_every: int


def nominal_values(sim: Simulator) -> torch.Tensor:
    """(4,) the params' k_s, k_b, k_d, mass."""
    return torch.tensor([float(getattr(sim.params, k)) for k in PHYSICAL], dtype=torch.float64)


def simulated_frames(sim: Simulator, moves: Moves, theta: torch.Tensor) -> torch.Tensor:
    """(S, M, F, N, 2): every move simulated under each of the S parameter sets theta (S, 4), at the recorded
    frame times (a rope that settled before the last frame stays where it settled)."""
    s, m = theta.shape[0], moves.start.shape[0]
    values = torch.exp(theta) * nominal_values(sim).to(theta)                       # (S, 4)
    per_rope = values.repeat_interleave(m, dim=0)                                   # (S M, 4)
    physics = Physics(*per_rope.unbind(-1))
    pos = moves.start.to(sim.dtype).repeat(s, 1, 1)
    _, info = sim.move(pos, moves.node.repeat(s), moves.delta.to(sim.dtype).repeat(s, 1), return_info=True,
                       record_every=moves.record_every, physics=physics, differentiable_frames=True)
    on_grid = info.frames[: 1 + int(info.substeps.max()) // moves.record_every]     # frames at k = 0, K, 2K, ...
    f = moves.frames.shape[1]
    if on_grid.shape[0] < f:                                                        # every rope settled earlier
        on_grid = torch.cat([on_grid, on_grid[-1:].expand(f - on_grid.shape[0], *on_grid.shape[1:])])
    return on_grid[:f].permute(1, 0, 2, 3).reshape(s, m, f, *moves.start.shape[1:])


def residuals(sim: Simulator, moves: Moves, theta: torch.Tensor) -> torch.Tensor:
    """(S, R) simulated minus recorded node coordinates [m] over the visible entries, for each parameter set."""
    sim_frames = simulated_frames(sim, moves, theta)
    mask = moves.visible.unsqueeze(-1).expand_as(moves.frames)
    recorded = torch.nan_to_num(moves.frames.to(sim_frames.dtype))
    return (sim_frames - recorded)[:, mask]


@dataclasses.dataclass
class Fit:
    theta: torch.Tensor            # (4,) the best start's log(value / nominal)
    values: dict[str, float]       # the fitted k_s, k_b, k_d, mass
    rms: float                     # root mean square position error [m] at the fit
    history: list[float]           # the best start's rms per iteration
    starts: torch.Tensor           # (S, 4) every start's final theta
    start_rms: list[float]
    simulator_calls: int           # batched forward + backward passes


def fit(sim: Simulator, moves: Moves, starts: int = 4, iterations: int = 150, lr: float = 0.08,
        bound: float = math.log(4.0), seed: int = 0) -> Fit:
    """Adam on the mean squared position error from ``starts`` initial guesses at once (the first: the nominal
    parameters; the others drawn log-uniformly within the bound from ``seed``)."""
    g = torch.Generator().manual_seed(seed)
    init = torch.zeros(starts, 4, dtype=torch.float64)
    if starts > 1:
        init[1:] = (torch.rand(starts - 1, 4, generator=g, dtype=torch.float64) * 2 - 1) * bound
    theta = init.clone().requires_grad_(True)
    opt = torch.optim.Adam([theta], lr=lr)
    history: list[torch.Tensor] = []
    for _ in range(iterations):
        opt.zero_grad()
        per_start = residuals(sim, moves, theta).pow(2).mean(1)                    # (S,)
        per_start.sum().backward()
        opt.step()
        with torch.no_grad():
            theta.clamp_(-bound, bound)
        history.append(per_start.detach())
    with torch.no_grad():
        final = residuals(sim, moves, theta).pow(2).mean(1)
    best = int(final.argmin())
    values = torch.exp(theta[best].detach()) * nominal_values(sim)
    return Fit(theta[best].detach().clone(), dict(zip(PHYSICAL, values.tolist())), float(final[best].sqrt()),
               [float(h[best].sqrt()) for h in history], theta.detach().clone(), final.sqrt().tolist(),
               2 * iterations + 1)


def identifiability(sim: Simulator, moves: Moves, theta: torch.Tensor, step: float = 1e-3,
                    identifiable_std: float = 0.05) -> dict[str, Any]:
    """What the recorded moves determine at ``theta`` (4,): eigenvalues of the Gauss-Newton curvature J^T J in log
    parameters, and per named combination (COMBINATIONS) its fitted value, standard deviation (relative: a std of
    0.02 is 2 %) and whether it is identifiable. J by central differences of the residuals (one batched call)."""
    eye = torch.eye(4, dtype=torch.float64) * step
    probes = torch.cat([theta + eye, theta - eye, theta[None]])                     # (9, 4)
    with torch.no_grad():
        r = residuals(sim, moves, probes)
    jac = ((r[:4] - r[4:8]) / (2 * step)).T                                         # (R, 4)
    curvature = jac.T @ jac
    dof = max(r.shape[1] - 4, 1)
    sigma2 = float(r[8].pow(2).sum()) / dof
    eigenvalues, eigenvectors = torch.linalg.eigh(curvature)
    cutoff = float(eigenvalues.max()) * 1e-10
    inverse = sum((eigenvectors[:, i:i + 1] @ eigenvectors[:, i:i + 1].T) / eigenvalues[i]
                  for i in range(4) if eigenvalues[i] > cutoff)
    values = torch.exp(theta) * nominal_values(sim)
    report = {}
    for name, c in COMBINATIONS.items():
        c = torch.tensor(c, dtype=torch.float64)
        in_span = float((eigenvectors[:, eigenvalues > cutoff].T @ c).norm() / c.norm()) > 1 - 1e-9
        std = math.sqrt(sigma2 * float(c @ inverse @ c)) if in_span else math.inf
        report[name] = {"fitted": float(torch.exp((c * torch.log(values)).sum())), "std": std,
                        "identifiable": std < identifiable_std}
    return {"eigenvalues": eigenvalues.tolist(), "eigenvectors": eigenvectors.T.tolist(), "sigma_m": math.sqrt(sigma2),
            "combinations": report, "simulator_calls": 1}
