"""Fit the cable's physical parameters to recorded moves by gradient descent through the simulator, and say what the
data can identify.

The recorded moves are independent given their start shapes (each starts from the rope at rest), so every move of a
recording and every start of the fit is simulated in ONE batched ``Simulator.move`` with per-rope parameters
(``diffdlo.Physics``, on the fused kernel with its adjoint): candidate s of S, move m of M is rope s * M + m. The
parameters are fitted in log space relative to nominal ones, theta = log(value / nominal), bounded to ``bound``
(default |theta| <= log 4), on the mean squared node-position error over the visible recorded frames: by
Levenberg-Marquardt (``fit_gauss_newton``, the default; its Jacobian by finite differences, all probes in the same
batched call) or by Adam on the autograd gradient (``fit``).

The start shapes are unknowns too (``fit_starts``, the default): a recorded start frame carries the tracker's noise,
and a move replayed from a noisy start shape relaxes that noise away (its stretching in milliseconds), which the
recording never shows; fitting the ratios to it biases them (errors in variables). Each move's start is corrected by
its own 2N offsets, measured by the move's frames (frame 0 included); the Gauss-Newton system is then block-arrow
shaped and the starts are eliminated move by move (``Linearization.step``).

Scaling all four parameters by one factor leaves every trajectory exactly as it is (forces and masses scale
together), so absolute values are never identifiable from positions, only ratios.

Identifiability: in this overdamped regime (inertia time ~0.1 ms against moves of ~1 s) the trajectories depend on
the ratios of the stiffnesses to the damping, k_s/k_d and k_b/k_d, and hardly on the mass; settled shapes alone
would only give k_b/k_s. ``identifiability`` measures it from the data: the Gauss-Newton curvature J^T J of the
residuals in theta (J by central differences, the start shapes marginalized), its eigenvalues, and for each named combination (a direction in
theta) its standard deviation sigma sqrt(c^T (J^T J)^+ c), sigma estimated from the fit's residual. A combination is
identifiable when its standard deviation is below ``identifiable_std`` (default 0.05: 5 %).
"""
from __future__ import annotations

import dataclasses
import math
import sys
import time
from typing import Any

import torch

from ..planar.physics import PHYSICAL, Physics
from ..planar.simulator import Simulator

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

    def subset(self, index: torch.Tensor) -> "Moves":
        """Only the moves at ``index`` (M',)."""
        return Moves(self.start[index], self.node[index], self.delta[index], self.frames[index], self.visible[index],
                     self.record_every)


def nominal_values(sim: Simulator) -> torch.Tensor:
    """(4,) the params' k_s, k_b, k_d, mass."""
    return torch.tensor([float(getattr(sim.params, k)) for k in PHYSICAL], dtype=torch.float64)


def simulated_frames(sim: Simulator, moves: Moves, theta: torch.Tensor,
                     offsets: torch.Tensor | None = None) -> torch.Tensor:
    """(S, M, F, N, 2): every move simulated under each of the S parameter sets theta (S, 4), at the recorded
    frame times (a rope that settled before the last frame stays where it settled). ``offsets`` (S, M, N, 2):
    corrections to the recorded start shapes (the fitted starts); None replays the recorded starts."""
    s, (m, n) = theta.shape[0], moves.start.shape[:2]
    values = torch.exp(theta) * nominal_values(sim).to(theta)                       # (S, 4)
    per_rope = values.repeat_interleave(m, dim=0)                                   # (S M, 4)
    physics = Physics(*per_rope.unbind(-1))
    pos = moves.start.to(sim.dtype).expand(s, m, n, 2)
    if offsets is not None:
        pos = pos + offsets.to(sim.dtype)
    _, info = sim.move(pos.reshape(s * m, n, 2), moves.node.repeat(s), moves.delta.to(sim.dtype).repeat(s, 1),
                       return_info=True, record_every=moves.record_every, physics=physics, differentiable_frames=True)
    on_grid = info.frames[: 1 + int(info.substeps.max()) // moves.record_every]     # frames at k = 0, K, 2K, ...
    f = moves.frames.shape[1]
    if on_grid.shape[0] < f:                                                        # every rope settled earlier
        on_grid = torch.cat([on_grid, on_grid[-1:].expand(f - on_grid.shape[0], *on_grid.shape[1:])])
    return on_grid[:f].permute(1, 0, 2, 3).reshape(s, m, f, n, 2)


def move_residuals(sim: Simulator, moves: Moves, theta: torch.Tensor,
                   offsets: torch.Tensor | None = None) -> torch.Tensor:
    """(S, M, F N 2) simulated minus recorded node coordinates [m] per move, 0 where not recorded."""
    sim_frames = simulated_frames(sim, moves, theta, offsets)
    seen = moves.visible.unsqueeze(-1).to(sim_frames.dtype)
    diff = (sim_frames - torch.nan_to_num(moves.frames.to(sim_frames.dtype))) * seen
    return diff.flatten(2)


def residuals(sim: Simulator, moves: Moves, theta: torch.Tensor, offsets: torch.Tensor | None = None) -> torch.Tensor:
    """(S, R) simulated minus recorded node coordinates [m] over the visible entries, for each parameter set."""
    mask = moves.visible.unsqueeze(-1).expand_as(moves.frames).flatten(1)
    return move_residuals(sim, moves, theta, offsets)[:, mask]


def compared(moves: Moves) -> int:
    """How many recorded coordinates the residuals compare."""
    return 2 * int(moves.visible.sum())


@dataclasses.dataclass
class Linearization:
    """The residuals of S candidates and their Jacobians, by move: ``r`` (S, M, D) (0 where not recorded),
    ``j_theta`` (S, M, D, 4) in the log parameters, ``j_start`` (S, M, D, 2N) in the move's own start coordinates
    (None when the starts are not fitted). A move's residuals depend on its own start only, so the Gauss-Newton
    system is block-arrow shaped: the starts are eliminated move by move (a Schur complement, as in bundle
    adjustment) and only a 4 x 4 system in theta is left."""
    r: torch.Tensor
    j_theta: torch.Tensor
    j_start: torch.Tensor | None
    count: int

    def cost(self) -> torch.Tensor:
        """(S,) mean squared residual."""
        return self.r.pow(2).sum((1, 2)) / self.count

    def where(self, keep: torch.Tensor, other: "Linearization") -> "Linearization":
        """Per candidate: this one's rows where ``keep`` (S,), else other's."""
        pick = lambda a, b: None if a is None else torch.where(keep.view(-1, *[1] * (a.ndim - 1)), a, b)
        return Linearization(pick(self.r, other.r), pick(self.j_theta, other.j_theta),
                             pick(self.j_start, other.j_start), self.count)

    def pick(self, i: int) -> "Linearization":
        return Linearization(self.r[i:i + 1], self.j_theta[i:i + 1],
                             None if self.j_start is None else self.j_start[i:i + 1], self.count)

    def _blocks(self):
        jt, r = self.j_theta, self.r.unsqueeze(-1)
        h_tt = (jt.transpose(-1, -2) @ jt).sum(1)                                    # (S, 4, 4)
        g_t = (jt.transpose(-1, -2) @ r).sum(1).squeeze(-1)                          # (S, 4)
        if self.j_start is None:
            return h_tt, g_t, None, None, None
        ju = self.j_start
        h_tu = jt.transpose(-1, -2) @ ju                                              # (S, M, 4, 2N)
        h_uu = ju.transpose(-1, -2) @ ju                                              # (S, M, 2N, 2N)
        g_u = (ju.transpose(-1, -2) @ r).squeeze(-1)                                  # (S, M, 2N)
        return h_tt, g_t, h_tu, h_uu, g_u

    def step(self, lam: torch.Tensor, hold: tuple[int, ...] = (),
             max_step: float = math.inf) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The Levenberg-Marquardt step (d theta (S, 4), d start (S, M, N, 2) or None) at damping ``lam`` (S,),
        Marquardt-scaled. ``hold``: indices of parameters kept where they are; ``max_step``: the longest step in
        any log parameter (the whole step is shortened to it)."""
        h_tt, g_t, h_tu, h_uu, g_u = self._blocks()
        if hold:
            keep = torch.ones(4, dtype=h_tt.dtype)
            keep[list(hold)] = 0
            h_tt = h_tt * keep[:, None] * keep + torch.diag(1 - keep)
            g_t = g_t * keep
            h_tu = None if h_tu is None else h_tu * keep[:, None]
        damp = lambda h, l: h + l * torch.diag_embed(h.diagonal(dim1=-2, dim2=-1)) \
            + 1e-12 * torch.eye(h.shape[-1], dtype=h.dtype)
        h_tt = damp(h_tt, lam.view(-1, 1, 1))
        if h_uu is None:
            d_theta = -torch.linalg.solve(h_tt, g_t)
            return d_theta * _shortening(d_theta, max_step)[:, None], None
        h_uu = damp(h_uu, lam.view(-1, 1, 1, 1))
        x_tu = torch.linalg.solve(h_uu, h_tu.transpose(-1, -2))                       # (S, M, 2N, 4)
        x_g = torch.linalg.solve(h_uu, g_u.unsqueeze(-1))                             # (S, M, 2N, 1)
        reduced = h_tt - (h_tu @ x_tu).sum(1)
        rhs = g_t - (h_tu @ x_g).sum(1).squeeze(-1)
        d_theta = -torch.linalg.solve(reduced, rhs)
        d_start = -(x_g + x_tu @ d_theta[:, None, :, None]).squeeze(-1)               # (S, M, 2N)
        factor = _shortening(d_theta, max_step)
        return d_theta * factor[:, None], (d_start * factor[:, None, None]).view(*d_start.shape[:2], -1, 2)

    def curvature(self) -> torch.Tensor:
        """(S, 4, 4) the Gauss-Newton curvature in theta with the start shapes marginalized (when fitted)."""
        h_tt, _, h_tu, h_uu, _ = self._blocks()
        if h_uu is None:
            return h_tt
        return h_tt - (h_tu @ torch.linalg.solve(h_uu, h_tu.transpose(-1, -2))).sum(1)

    def unknowns(self) -> int:
        return 4 + (0 if self.j_start is None else self.j_start.shape[1] * self.j_start.shape[-1])


def _shortening(d_theta: torch.Tensor, max_step: float) -> torch.Tensor:
    """(S,) the factor <= 1 that shortens each step to ``max_step`` in its longest log parameter."""
    return (max_step / d_theta.abs().amax(-1).clamp_min(1e-300)).clamp(max=1.0)


def linearize(sim: Simulator, moves: Moves, theta: torch.Tensor, offsets: torch.Tensor | None = None,
              fit_starts: bool = False, step: float = 1e-3, start_step: float = 1e-5,
              free: tuple[int, ...] = (0, 1, 2, 3)) -> Linearization:
    """Residuals and Jacobians at the S candidates theta (S, 4) (and start corrections ``offsets`` (S, M, N, 2)):
    central differences in the ``free`` log parameters (the others' columns are 0) and, with ``fit_starts``,
    forward differences in each
    start coordinate (``start_step`` [m]; one probe moves that coordinate in every move at once, since a move
    depends on its own start only): 2 len(free) + 1 + 2N probes per candidate, all in ONE batched simulator call."""
    s, (m, n) = theta.shape[0], moves.start.shape[:2]
    offsets = torch.zeros(s, m, n, 2, dtype=torch.float64) if offsets is None else offsets
    q = len(free)
    eye = (torch.eye(4, dtype=theta.dtype) * step)[list(free)]
    thetas = [theta[:, None] + eye, theta[:, None] - eye, theta[:, None]]
    starts = [offsets[:, None].expand(s, 2 * q + 1, m, n, 2)]
    if fit_starts:
        k = 2 * n
        nudge = (torch.eye(k, dtype=offsets.dtype) * start_step).view(k, 1, n, 2)
        thetas.append(theta[:, None].expand(s, k, 4))
        starts.append(offsets[:, None] + nudge)
    probes, probe_starts = torch.cat(thetas, 1), torch.cat(starts, 1)
    p = probes.shape[1]
    with torch.no_grad():
        r = move_residuals(sim, moves, probes.reshape(s * p, 4), probe_starts.reshape(s * p, m, n, 2))
    r = r.view(s, p, m, -1)
    base = r[:, 2 * q]
    j_theta = torch.zeros(s, m, r.shape[-1], 4, dtype=r.dtype)
    j_theta[..., list(free)] = ((r[:, :q] - r[:, q:2 * q]) / (2 * step)).permute(0, 2, 3, 1)
    j_start = ((r[:, 2 * q + 1:] - base[:, None]) / start_step).permute(0, 2, 3, 1) if fit_starts else None
    return Linearization(base, j_theta, j_start, compared(moves))


@dataclasses.dataclass
class Fit:
    theta: torch.Tensor            # (4,) the best start's log(value / nominal)
    values: dict[str, float]       # the fitted k_s, k_b, k_d, mass
    rms: float                     # root mean square position error [m] at the fit
    history: list[float]           # the best start's rms per iteration
    starts: torch.Tensor           # (S, 4) every start's final theta
    start_rms: list[float]
    simulator_calls: int           # batched forward (+ backward) passes
    offsets: torch.Tensor | None = None     # (M', N, 2) the best start's corrections to the kept moves' starts
    at_best: Linearization | None = None    # Levenberg-Marquardt holding nothing: residuals and Jacobians there
    kept: torch.Tensor | None = None        # (M',) the moves fitted (Levenberg-Marquardt leaves out outliers)
    left_out: dict[int, float] = dataclasses.field(default_factory=dict)   # move -> its rms [m] when left out


def _bar(iterations: int, method: str, progress: bool):
    from tqdm import tqdm
    return tqdm(range(iterations), desc=f"calibrate ({method})", disable=not progress, dynamic_ncols=True,
                file=sys.stderr)


def _fitted(sim: Simulator, theta: torch.Tensor) -> dict[str, float]:
    return dict(zip(PHYSICAL, (torch.exp(theta) * nominal_values(sim)).tolist()))


def fit(sim: Simulator, moves: Moves, starts: int = 4, iterations: int = 150, lr: float = 0.08,
        bound: float = math.log(4.0), seed: int = 0, fit_starts: bool = False, progress: bool = False) -> Fit:
    """Adam on the mean squared position error from ``starts`` initial guesses at once (the first: the nominal
    parameters; the others drawn log-uniformly within the bound from ``seed``); with ``fit_starts`` the start
    shapes' corrections too (in mm, the same learning rate). ``fit_gauss_newton`` converges in far fewer simulator
    calls on this least-squares problem; Adam is kept for comparison."""
    s, (m, n) = starts, moves.start.shape[:2]
    theta = initial_thetas(starts, bound, seed).requires_grad_(True)
    offsets_mm = torch.zeros(s, m, n, 2, dtype=torch.float64, requires_grad=fit_starts)
    opt = torch.optim.Adam([theta, offsets_mm] if fit_starts else [theta], lr=lr)
    history: list[torch.Tensor] = []
    for _ in (bar := _bar(iterations, "adam", progress)):
        opt.zero_grad()
        per_start = move_residuals(sim, moves, theta, 1e-3 * offsets_mm).pow(2).sum((1, 2)) / compared(moves)
        per_start.sum().backward()
        opt.step()
        with torch.no_grad():
            theta.clamp_(-bound, bound)
        history.append(per_start.detach())
        bar.set_postfix(rms_mm=f"{1000 * float(per_start.detach().min().sqrt()):.3f}")
    with torch.no_grad():
        final = move_residuals(sim, moves, theta, 1e-3 * offsets_mm).pow(2).sum((1, 2)) / compared(moves)
    best = int(final.argmin())
    return Fit(theta[best].detach().clone(), _fitted(sim, theta[best].detach()), float(final[best].sqrt()),
               [float(h[best].sqrt()) for h in history], theta.detach().clone(), final.sqrt().tolist(),
               2 * iterations + 1, 1e-3 * offsets_mm[best].detach().clone() if fit_starts else None)


def initial_thetas(starts: int, bound: float, seed: int) -> torch.Tensor:
    """(starts, 4): the nominal parameters first, then guesses drawn log-uniformly within the bound from seed."""
    g = torch.Generator().manual_seed(seed)
    init = torch.zeros(starts, 4, dtype=torch.float64)
    if starts > 1:
        init[1:] = (torch.rand(starts - 1, 4, generator=g, dtype=torch.float64) * 2 - 1) * bound
    return init


def fit_gauss_newton(sim: Simulator, moves: Moves, starts: int = 1, iterations: int = 12,
                     bound: float = math.log(4.0), seed: int = 0, damping: float = 1e-3, fit_starts: bool = True,
                     hold: tuple[str, ...] = ("k_d", "mass"), max_step: float = 1.0,
                     outlier_factor: float | None = 2.0, tol: float = 1e-7, progress: bool = False) -> Fit:
    """Levenberg-Marquardt on the position residuals: each iteration one batched call (``linearize``), a damped
    Gauss-Newton step per start, kept if it lowers the error (the damping then shrinks) and refused otherwise (it
    grows), until an accepted step gains less than ``tol`` (relative) or ``iterations`` are done; a step is at most ``max_step`` in any log parameter. The parameters in ``hold`` keep their start values:
    by default k_d, because positions fix only ratios (one parameter sets the scale, and the report flags absolute
    values as unidentifiable), and the mass, because in this overdamped regime the trajectories hardly depend on
    mass/k_d (inertia time ~0.1 ms): that direction is nearly flat, a Gauss-Newton step along it fits the noise and
    runs into the bound, and the fit stalls there (measured on 2 of 10 synthetic seeds). ``identifiability``
    still reports all four parameters' combinations, mass/k_d included.

    Stages, ``iterations`` each: (1) theta on the recorded starts; (2) with ``fit_starts`` (default) theta and each
    move's start shape together: the recorded start frames carry the tracker's noise, and replaying a move from a
    noisy start biases the ratios (errors in variables: -0.02 % and +3.12 % on k_s/k_d and k_b/k_d at 1 mm noise
    without it, measured); the starts come second so that they do not absorb a wrong theta's error. (3) Moves
    whose rms error is still above ``outlier_factor`` times the median move's are left out and the last stage runs
    again on the rest: a move replayed from a noisy start can take another branch (a tight fold bending the other
    way) that no small correction of the start brings back (measured: 1 move of 20 on synthetic seed 2); a move
    within 1 um is never left out. None keeps every move."""
    s = starts
    theta = initial_thetas(starts, bound, seed)
    held = tuple(PHYSICAL.index(k) for k in hold)
    free = tuple(i for i in range(4) if i not in held)           # only these are probed
    history: list[torch.Tensor] = []
    calls = 0
    kept = torch.arange(moves.start.shape[0])
    left_out: dict[int, float] = {}

    def run(part: Moves, theta, fits_starts, label):
        nonlocal calls
        offsets = torch.zeros(s, *part.start.shape, dtype=torch.float64)
        lin = linearize(sim, part, theta, offsets, fits_starts, free=free)
        cost = lin.cost()
        lam = torch.full((starts,), damping, dtype=torch.float64)
        history.append(cost)
        for _ in (bar := _bar(iterations, label, progress)):
            d_theta, d_start = lin.step(lam, held, max_step)
            trial = (theta + d_theta).clamp(-bound, bound)
            trial_offsets = offsets if d_start is None else offsets + d_start
            trial_lin = linearize(sim, part, trial, trial_offsets, fits_starts, free=free)
            trial_cost = trial_lin.cost()
            better = trial_cost < cost
            theta = torch.where(better[:, None], trial, theta)
            offsets = torch.where(better.view(-1, 1, 1, 1), trial_offsets, offsets)
            lin = trial_lin.where(better, lin)
            cost = torch.where(better, trial_cost, cost)
            gain = torch.where(better, history[-1] - cost, torch.zeros_like(cost)) / cost.clamp_min(1e-300)
            lam = torch.where(better, lam / 3, lam * 5)
            history.append(cost)
            calls += 1
            bar.set_postfix(rms_mm=f"{1000 * float(cost.min().sqrt()):.3f}")
            if bool((better & (gain < tol)).all() | (lam > 1e4).all()):
                break                                       # converged: accepted steps no longer gain
        calls += 1
        return theta, offsets, lin, cost

    theta, offsets, lin, cost = run(moves, theta, False, "gauss-newton")
    if fit_starts:
        theta, offsets, lin, cost = run(moves, theta, True, "gauss-newton, start shapes")
    if outlier_factor is not None:
        best = int(cost.argmin())
        per_move = (lin.r[best].pow(2).sum(-1) / (2 * moves.visible.sum((1, 2)).clamp_min(1))).sqrt()
        outliers = (per_move > outlier_factor * per_move.median()) & (per_move > 1e-6)   # below 1 um: rounding
        if bool(outliers.any()):
            left_out = {int(i): float(per_move[i]) for i in outliers.nonzero().flatten()}
            kept = (~outliers).nonzero().flatten()
            theta, offsets, lin, cost = run(moves.subset(kept), theta, fit_starts, "gauss-newton, outliers left out")
    best = int(cost.argmin())
    return Fit(theta[best].clone(), _fitted(sim, theta[best]), float(cost[best].sqrt()),
               [float(h[best].sqrt()) for h in history], theta.clone(), cost.sqrt().tolist(), calls,
               offsets[best].clone() if fit_starts else None, None if held else lin.pick(best), kept, left_out)


def identifiability(sim: Simulator, moves: Moves, theta: torch.Tensor, offsets: torch.Tensor | None = None,
                    fit_starts: bool | None = None, step: float = 1e-3, identifiable_std: float = 0.05,
                    at_theta: Linearization | None = None) -> dict[str, Any]:
    """What the recorded moves determine at ``theta`` (4,) (and start corrections ``offsets`` (M, N, 2)):
    eigenvalues of the Gauss-Newton curvature J^T J in log parameters (with the start shapes marginalized when they
    are fitted), and per named combination (COMBINATIONS) its fitted value, standard deviation (relative: a std of
    0.02 is 2 %) and whether it is identifiable. ``at_theta``: the fit's own linearization there (no call)."""
    calls_saved = at_theta is not None
    if at_theta is None:
        fit_starts = offsets is not None if fit_starts is None else fit_starts
        at_theta = linearize(sim, moves, theta[None], None if offsets is None else offsets[None], fit_starts, step)
    # the common scale of all four is an exact symmetry (forces and masses scale together): projected out, since
    # finite differences leave a spurious small curvature along it (measured: k_s "identifiable" on 1 seed of 10)
    scale = torch.full((4, 1), 0.5, dtype=torch.float64)
    projector = torch.eye(4, dtype=torch.float64) - scale @ scale.T
    curvature = projector @ at_theta.curvature()[0] @ projector
    dof = max(at_theta.count - at_theta.unknowns(), 1)
    sigma2 = float(at_theta.r.pow(2).sum()) / dof
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
            "combinations": report, "simulator_calls": 0 if calls_saved else 1}


# ====================================================================== from a recording
def moves_from_recording(rec, dt: float, record_every: int | None = None) -> Moves:
    """The recorded moves on the simulator's frame grid: each move starts from its start frame (the rope at rest,
    every node tracked), and its frames at multiples of ``record_every`` substeps after the start are compared
    (others are left out). ``record_every`` default: the recording's meta, else the shortest frame spacing."""
    if record_every is None:
        spacing = float((rec.times[1:] - rec.times[:-1]).min()) if rec.n_frames > 1 else dt
        record_every = int(rec.meta.get("record_every") or max(1, round(spacing / dt)))
    m, n = rec.n_moves, rec.n_nodes
    grids = []
    for i in range(m):
        s, e = int(rec.move_start[i]), int(rec.move_end[i])
        if not bool(rec.visible[s].all()):
            missing = (~rec.visible[s]).nonzero().flatten().tolist()
            raise ValueError(f"move {i} starts from frame {s}, where nodes {missing} were not tracked: a replay "
                             "needs the whole start shape")
        steps = torch.round((rec.times[s:e + 1] - rec.times[s]) / dt).to(torch.int64)
        on_grid = (steps % record_every == 0).nonzero().flatten()
        grids.append((s + on_grid, steps[on_grid] // record_every))
    f = int(max(int(j.max()) for _, j in grids)) + 1
    frames = torch.full((m, f, n, 2), math.nan, dtype=torch.float64)
    visible = torch.zeros(m, f, n, dtype=torch.bool)
    for i, (rows, j) in enumerate(grids):
        frames[i, j] = rec.positions[rows]
        visible[i, j] = rec.visible[rows]
    return Moves(rec.positions[rec.move_start].clone(), rec.move_node.clone(), rec.move_delta.clone(), frames,
                 visible, record_every)


# ====================================================================== command line
def synthetic_scale(seed: int) -> dict[str, float]:
    """The hidden rope of ``--synthetic``: each parameter scaled by a factor log-uniform in [0.5, 2] (from seed)."""
    g = torch.Generator().manual_seed(seed)
    u = torch.rand(len(PHYSICAL), generator=g, dtype=torch.float64) * 2 - 1
    return {k: float(torch.exp(v * math.log(2.0))) for k, v in zip(PHYSICAL, u)}


def report(ident: dict[str, Any], true: dict[str, float] | None) -> dict[str, Any]:
    """Per parameter and named combination: fitted, true (synthetic data), rel_error, std, identifiable."""
    rows = {}
    for name, c in COMBINATIONS.items():
        row = dict(ident["combinations"][name])
        if true is not None:
            t = math.exp(sum(ci * math.log(true[k]) for ci, k in zip(c, PHYSICAL)))
            row.update(true=t, rel_error=row["fitted"] / t - 1.0)
        rows[name] = row
    return rows


def plot_trajectories(sim: Simulator, moves: Moves, theta: torch.Tensor, path, count: int = 4,
                      offsets: torch.Tensor | None = None) -> None:
    """Recorded (dots) against simulated (lines) paths of the grasped node and of node 0 in the first moves."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    with torch.no_grad():
        simulated = simulated_frames(sim, moves, theta[None], None if offsets is None else offsets[None])[0]
    count = min(count, moves.start.shape[0])
    fig, axes = plt.subplots(1, count, figsize=(3.4 * count, 3.4), squeeze=False)
    for i, ax in enumerate(axes[0]):
        for node, colour in ((int(moves.node[i]), "tab:red"), (0, "tab:blue")):
            rec = moves.frames[i, :, node][moves.visible[i, :, node]]
            ax.plot(rec[:, 0], rec[:, 1], ".", color=colour, ms=4, label=f"recorded node {node}")
            ax.plot(simulated[i, :, node, 0], simulated[i, :, node, 1], "-", color=colour, lw=1,
                    label=f"simulated node {node}")
        ax.set_title(f"move {i}", fontsize=9)
        ax.set_aspect("equal", adjustable="datalim")
        ax.tick_params(labelsize=7)
        ax.legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    import argparse
    from pathlib import Path

    import yaml

    from ..utils.files import check_fresh_out, out_lock
    from ..planar.params import ParamsError, load_params
    from .record import make_recording
    from .recording import RecordingError, load_recording

    ap = argparse.ArgumentParser(prog="python -m diffdlo.calibration.calibrate", description=__doc__.split("\n\n")[0])
    source = ap.add_mutually_exclusive_group(required=True)
    source.add_argument("--data", help="a recording (.npz, see diffdlo/calibration/recording.py)")
    source.add_argument("--synthetic", action="store_true",
                        help="record a hidden rope (parameters x0.5-x2 of --params, log-uniform from --seed) first")
    ap.add_argument("--out", required=True, help="output folder: results.json, trajectories.png")
    ap.add_argument("--params", default="cable", help="the nominal model's params (default cable)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override a cable parameter of --params, e.g. --set n_nodes=6 (small test ropes)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--moves", type=int, default=20, help="--synthetic: recorded moves (default 20)")
    ap.add_argument("--noise", type=float, default=0.001, help="--synthetic: position noise std [m] (default 1 mm)")
    ap.add_argument("--record-every", type=int, default=50, help="--synthetic: substeps between frames (default 50)")
    ap.add_argument("--method", choices=("gauss-newton", "adam"), default="gauss-newton",
                    help="Levenberg-Marquardt with a finite-difference Jacobian (default), or Adam on the gradient")
    ap.add_argument("--starts", type=int, default=4,
                    help="initial guesses fitted at once: the nominal and random ones (default 4; with 1, 1 of 10 "
                         "synthetic seeds ended in a local optimum)")
    ap.add_argument("--hold", default="k_d,mass",
                    help="gauss-newton: parameters kept at their nominal values, comma-separated, or 'none' (default "
                         "k_d,mass: one must set the scale, and mass/k_d is nearly flat)")
    ap.add_argument("--recorded-starts", action="store_true",
                    help="replay each move from its recorded start frame instead of fitting the start shapes too "
                         "(faster; biased by the start frames' noise)")
    ap.add_argument("--iterations", type=int, default=None,
                    help="iterations (default 12 for gauss-newton, 150 for adam)")
    ap.add_argument("--lr", type=float, default=0.08, help="adam: learning rate on log parameters (default 0.08)")
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    ap.add_argument("--overwrite", action="store_true", help="replace an earlier result in --out")
    ap.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    args = ap.parse_args(argv)
    if args.iterations is None:
        args.iterations = 12 if args.method == "gauss-newton" else 150
    for flag, value, least in (("--moves", args.moves, 1), ("--starts", args.starts, 1),
                               ("--record-every", args.record_every, 1),
                               ("--iterations", args.iterations, 1), ("--threads", args.threads, 1)):
        if value < least:
            ap.error(f"{flag} must be at least {least}, got {value}")
    if not (math.isfinite(args.noise) and args.noise >= 0) or not (math.isfinite(args.lr) and args.lr > 0):
        ap.error(f"--noise must be >= 0 and --lr > 0, got {args.noise} and {args.lr}")
    hold = () if args.hold.strip() == "none" else tuple(k.strip() for k in args.hold.split(",") if k.strip())
    bad = [k for k in hold if k not in PHYSICAL]
    if bad or len(set(hold)) == len(PHYSICAL):
        ap.error(f"--hold must name some of {', '.join(PHYSICAL)} (not all) or 'none', got {args.hold!r}")
    try:
        pairs = [item.split("=", 1) for item in args.set]
        if any(len(p) != 2 for p in pairs):
            raise ValueError(f"--set expects KEY=VALUE, got {args.set}")
        nominal = load_params(args.params, **{k.strip(): yaml.safe_load(v) for k, v in pairs})
        check_fresh_out(args.out, args.overwrite, "an earlier calibration")
        scale = synthetic_scale(args.seed) if args.synthetic else None
        rec = (make_recording(nominal, args.moves, args.seed, noise=args.noise, record_every=args.record_every,
                              scale=scale, params_name=args.params)
               if args.synthetic else load_recording(args.data, nominal))
        sim = Simulator(nominal, dtype=torch.float64)
        moves = moves_from_recording(rec, nominal.dt)
    except (ParamsError, RecordingError, FileExistsError, ValueError) as exc:
        ap.error(str(exc))
    torch.set_num_threads(args.threads)
    out = Path(args.out)
    from ..utils.signals import exit_code, stop_on_signals
    try:
        with out_lock(out), stop_on_signals():         # SIGINT/SIGTERM stop it however it was started
            results, result, fit_s = _calibrate(args, sim, moves, rec, nominal, hold, out)
    except KeyboardInterrupt as exc:
        print(f"calibrate: stopped by {exc or 'SIGINT'}: no results written", file=sys.stderr)
        return exit_code(exc)
    for name, row in results["parameters"].items():
        extra = f", true {row['true']:.4g} ({100 * row['rel_error']:+.2f} %)" if "true" in row else ""
        print(f"{name:9s} fitted {row['fitted']:.4g}{extra}, std {100 * row['std']:.2g} %, "
              f"{'identifiable' if row['identifiable'] else 'NOT identifiable'}")
    print(f"rms {1000 * result.rms:.3f} mm over {results['frames_compared']} node frames, {fit_s:.0f} s, "
          f"{results['simulator_calls']} batched simulator calls -> {out / 'results.json'}")
    return 0


def _calibrate(args, sim, moves, rec, nominal, hold, out):
    """The fit, its identifiability and the run's results.json and picture. Returns (results, fit result, fit s)."""
    from ..utils.files import write_json_atomic
    t0 = time.perf_counter()
    fit_starts = not args.recorded_starts
    result = (fit_gauss_newton(sim, moves, starts=args.starts, iterations=args.iterations, seed=args.seed,
                               fit_starts=fit_starts, hold=hold, progress=not args.no_progress)
              if args.method == "gauss-newton" else
              fit(sim, moves, starts=args.starts, iterations=args.iterations, lr=args.lr, seed=args.seed,
                  fit_starts=fit_starts, progress=not args.no_progress))
    fit_s = time.perf_counter() - t0
    fitted_moves = moves if result.kept is None else moves.subset(result.kept)
    ident = identifiability(sim, fitted_moves, result.theta, result.offsets, fit_starts, at_theta=result.at_best)
    true = rec.meta.get("true_params") if args.synthetic else None
    results = {"data": "synthetic" if args.synthetic else str(args.data), "seed": args.seed, "method": args.method,
               "fit_starts": fit_starts, "noise": args.noise if args.synthetic else None,
               "held": list(hold) if args.method == "gauss-newton" else [],
               "moves_left_out": {str(k): v for k, v in result.left_out.items()},
               "moves": rec.n_moves, "frames_compared": int(moves.visible.sum()), "params": args.params,
               "nominal": {k: float(getattr(nominal, k)) for k in PHYSICAL}, "true": true,
               "fitted": result.values, "rms_m": result.rms, "start_rms_m": result.start_rms,
               "history_rms_m": result.history[::max(1, len(result.history) // 50)],
               "simulator_calls": result.simulator_calls + ident["simulator_calls"], "fit_s": fit_s,
               "eigenvalues": ident["eigenvalues"], "sigma_m": ident["sigma_m"],
               "parameters": report(ident, true)}
    write_json_atomic(out / "results.json", results)
    plot_trajectories(sim, fitted_moves, result.theta, out / "trajectories.png", offsets=result.offsets)
    return results, result, fit_s


if __name__ == "__main__":
    raise SystemExit(main())
