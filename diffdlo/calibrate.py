"""Fit the cable's physical parameters to recorded moves by gradient descent through the simulator, and say what the
data can identify.

The recorded moves are independent given their start shapes (each starts from the rope at rest), so every move of a
recording and every start of the fit is simulated in ONE batched ``Simulator.move`` with per-rope parameters
(``diffdlo.Physics``): candidate s of S, move m of M is rope s * M + m. The parameters are fitted in log space
relative to nominal ones, theta = log(value / nominal), bounded to ``bound`` (default |theta| <= log 4), on the mean
squared node-position error over the visible recorded frames: by Levenberg-Marquardt (``fit_gauss_newton``, the
default: 4 parameters, so the Jacobian by central differences is 8 extra ropes per move in the same batched call)
or by Adam on the autograd gradient (``fit``).

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
import sys
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
    at_best: tuple[torch.Tensor, torch.Tensor] | None = None   # Levenberg-Marquardt: residuals and Jacobian there


def _bar(iterations: int, method: str, progress: bool):
    from tqdm import tqdm
    return tqdm(range(iterations), desc=f"calibrate ({method})", disable=not progress, dynamic_ncols=True,
                file=sys.stderr)


def fit(sim: Simulator, moves: Moves, starts: int = 4, iterations: int = 150, lr: float = 0.08,
        bound: float = math.log(4.0), seed: int = 0, progress: bool = False) -> Fit:
    """Adam on the mean squared position error from ``starts`` initial guesses at once (the first: the nominal
    parameters; the others drawn log-uniformly within the bound from ``seed``). ``fit_gauss_newton`` converges in
    far fewer simulator calls on this small least-squares problem; Adam is kept for comparison."""
    theta = initial_thetas(starts, bound, seed).requires_grad_(True)
    opt = torch.optim.Adam([theta], lr=lr)
    history: list[torch.Tensor] = []
    for _ in (bar := _bar(iterations, "adam", progress)):
        opt.zero_grad()
        per_start = residuals(sim, moves, theta).pow(2).mean(1)                    # (S,)
        per_start.sum().backward()
        opt.step()
        with torch.no_grad():
            theta.clamp_(-bound, bound)
        history.append(per_start.detach())
        bar.set_postfix(rms_mm=f"{1000 * float(per_start.detach().min().sqrt()):.3f}")
    with torch.no_grad():
        final = residuals(sim, moves, theta).pow(2).mean(1)
    best = int(final.argmin())
    values = torch.exp(theta[best].detach()) * nominal_values(sim)
    return Fit(theta[best].detach().clone(), dict(zip(PHYSICAL, values.tolist())), float(final[best].sqrt()),
               [float(h[best].sqrt()) for h in history], theta.detach().clone(), final.sqrt().tolist(),
               2 * iterations + 1)


def residuals_and_jacobian(sim: Simulator, moves: Moves, theta: torch.Tensor,
                           step: float = 1e-3) -> tuple[torch.Tensor, torch.Tensor]:
    """Residuals (S, R) at the S parameter sets theta (S, 4) and their Jacobians (S, R, 4) in theta, by central
    differences: all 9 S probes in ONE batched simulator call, no backward pass."""
    s = theta.shape[0]
    eye = torch.eye(4, dtype=theta.dtype) * step
    probes = torch.cat([theta[:, None] + eye, theta[:, None] - eye, theta[:, None]], dim=1)   # (S, 9, 4)
    with torch.no_grad():
        r = residuals(sim, moves, probes.reshape(9 * s, 4)).view(s, 9, -1)
    return r[:, 8], ((r[:, :4] - r[:, 4:8]) / (2 * step)).transpose(1, 2)


def initial_thetas(starts: int, bound: float, seed: int) -> torch.Tensor:
    """(starts, 4): the nominal parameters first, then guesses drawn log-uniformly within the bound from seed."""
    g = torch.Generator().manual_seed(seed)
    init = torch.zeros(starts, 4, dtype=torch.float64)
    if starts > 1:
        init[1:] = (torch.rand(starts - 1, 4, generator=g, dtype=torch.float64) * 2 - 1) * bound
    return init


def fit_gauss_newton(sim: Simulator, moves: Moves, starts: int = 1, iterations: int = 12,
                     bound: float = math.log(4.0), seed: int = 0, damping: float = 1e-3,
                     progress: bool = False) -> Fit:
    """Levenberg-Marquardt on the position residuals: each iteration one batched call (the Jacobian by central
    differences, ``residuals_and_jacobian``), a damped Gauss-Newton step per start, kept if it lowers the error
    (the damping then shrinks) and refused otherwise (it grows). Marquardt's diagonal scaling handles the exact
    null direction (the common scale of all four parameters): the step leaves it where it starts."""
    theta = initial_thetas(starts, bound, seed)
    r, jac = residuals_and_jacobian(sim, moves, theta)
    cost = r.pow(2).mean(1)
    lam = torch.full((starts,), damping, dtype=torch.float64)
    history = [cost]
    for _ in (bar := _bar(iterations, "gauss-newton", progress)):
        h = jac.transpose(1, 2) @ jac                                                 # (S, 4, 4)
        g = (jac.transpose(1, 2) @ r.unsqueeze(-1)).squeeze(-1)                      # (S, 4)
        scaled = torch.diag_embed(h.diagonal(dim1=-2, dim2=-1)) + 1e-12 * torch.eye(4, dtype=torch.float64)
        step = -torch.linalg.solve(h + lam[:, None, None] * scaled, g)
        trial = (theta + step).clamp(-bound, bound)
        r_t, jac_t = residuals_and_jacobian(sim, moves, trial)
        cost_t = r_t.pow(2).mean(1)
        better = cost_t < cost
        theta = torch.where(better[:, None], trial, theta)
        r = torch.where(better[:, None], r_t, r)
        jac = torch.where(better[:, None, None], jac_t, jac)
        cost = torch.where(better, cost_t, cost)
        lam = torch.where(better, lam / 3, lam * 5)
        history.append(cost)
        bar.set_postfix(rms_mm=f"{1000 * float(cost.min().sqrt()):.3f}")
    best = int(cost.argmin())
    values = torch.exp(theta[best]) * nominal_values(sim)
    return Fit(theta[best].clone(), dict(zip(PHYSICAL, values.tolist())), float(cost[best].sqrt()),
               [float(h[best].sqrt()) for h in history], theta.clone(), cost.sqrt().tolist(), 1 + iterations,
               (r[best], jac[best]))


def identifiability(sim: Simulator, moves: Moves, theta: torch.Tensor, step: float = 1e-3,
                    identifiable_std: float = 0.05,
                    at_theta: tuple[torch.Tensor, torch.Tensor] | None = None) -> dict[str, Any]:
    """What the recorded moves determine at ``theta`` (4,): eigenvalues of the Gauss-Newton curvature J^T J in log
    parameters, and per named combination (COMBINATIONS) its fitted value, standard deviation (relative: a std of
    0.02 is 2 %) and whether it is identifiable. J by central differences of the residuals (one batched call)."""
    calls_saved = at_theta is not None
    if at_theta is None:                                    # else the fit's own, at this theta: no call needed
        r, jac = residuals_and_jacobian(sim, moves, theta[None], step)
        at_theta = (r[0], jac[0])
    r, jac = at_theta                                                               # (R,), (R, 4)
    curvature = jac.T @ jac
    dof = max(r.shape[0] - 4, 1)
    sigma2 = float(r.pow(2).sum()) / dof
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


def plot_trajectories(sim: Simulator, moves: Moves, theta: torch.Tensor, path, count: int = 4) -> None:
    """Recorded (dots) against simulated (lines) paths of the grasped node and of node 0 in the first moves."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    with torch.no_grad():
        simulated = simulated_frames(sim, moves, theta[None])[0]
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
    import time
    from pathlib import Path

    import yaml

    from .files import check_fresh_out, out_lock, write_json_atomic
    from .params import ParamsError, load_params
    from .record import make_recording
    from .recording import RecordingError, load_recording

    ap = argparse.ArgumentParser(prog="python -m diffdlo.calibrate", description=__doc__.split("\n\n")[0])
    source = ap.add_mutually_exclusive_group(required=True)
    source.add_argument("--data", help="a recording (.npz, see diffdlo/recording.py)")
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
    ap.add_argument("--starts", type=int, default=1, help="initial guesses fitted at once (default 1)")
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
        sim = Simulator(nominal, dtype=torch.float64, backend="torch")
        moves = moves_from_recording(rec, nominal.dt)
    except (ParamsError, RecordingError, FileExistsError, ValueError) as exc:
        ap.error(str(exc))
    torch.set_num_threads(args.threads)
    out = Path(args.out)
    with out_lock(out):
        t0 = time.perf_counter()
        result = (fit_gauss_newton(sim, moves, starts=args.starts, iterations=args.iterations, seed=args.seed,
                                   progress=not args.no_progress)
                  if args.method == "gauss-newton" else
                  fit(sim, moves, starts=args.starts, iterations=args.iterations, lr=args.lr, seed=args.seed,
                      progress=not args.no_progress))
        fit_s = time.perf_counter() - t0
        ident = identifiability(sim, moves, result.theta, at_theta=result.at_best)
        true = rec.meta.get("true_params") if args.synthetic else None
        results = {"data": "synthetic" if args.synthetic else str(args.data), "seed": args.seed, "method": args.method,
                   "moves": rec.n_moves, "frames_compared": int(moves.visible.sum()), "params": args.params,
                   "nominal": {k: float(getattr(nominal, k)) for k in PHYSICAL}, "true": true,
                   "fitted": result.values, "rms_m": result.rms, "start_rms_m": result.start_rms,
                   "history_rms_m": result.history[::max(1, len(result.history) // 50)],
                   "simulator_calls": result.simulator_calls + ident["simulator_calls"], "fit_s": fit_s,
                   "eigenvalues": ident["eigenvalues"], "sigma_m": ident["sigma_m"],
                   "parameters": report(ident, true)}
        write_json_atomic(out / "results.json", results)
        plot_trajectories(sim, moves, result.theta, out / "trajectories.png")
    for name, row in results["parameters"].items():
        extra = f", true {row['true']:.4g} ({100 * row['rel_error']:+.2f} %)" if "true" in row else ""
        print(f"{name:9s} fitted {row['fitted']:.4g}{extra}, std {100 * row['std']:.2g} %, "
              f"{'identifiable' if row['identifiable'] else 'NOT identifiable'}")
    print(f"rms {1000 * result.rms:.3f} mm over {results['frames_compared']} node frames, {fit_s:.0f} s, "
          f"{results['simulator_calls']} batched simulator calls -> {out / 'results.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
