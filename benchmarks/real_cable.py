"""The chain in 3-D fitted to DEFORM's real cables and scored by DEFORM's protocol (issue 61; docs/REAL_CABLE.md).

    python -m benchmarks.real_cable --data /path/to/DEFORM/data_set --out runs/real_cable [--cables 1 2 3 4 5]
                                    [--quick] [--jobs 2] [--threads 2] [--overwrite]

For each cable: fit the chain's physical parameters (diffdlo.chain3d.fit.fit_cable) on its train split (the fits run
in ``--jobs`` processes of one torch thread each), then score the open-loop prediction of every eval recording by
DEFORM's protocol (diffdlo.chain3d.fit.evaluate, with ``--threads`` torch threads, timed per trajectory-frame), beside
the "markers frozen at frame 1, held ones driven" baseline and the numbers DEFORM's paper reports.

Writes OUT/results.json (per cable: the errors, the fitted parameters with their uncertainty, the time per frame,
the command), OUT/predictions/DLO<k>/<id>.npz (``positions``: (T-2, n, 3) float32 [m], frames 2..T-1) and, where
matplotlib is installed (the ``plot`` extra), OUT/figures/: the error over time per cable and, per cable, a
recorded and a predicted cable side by side in 3-D at a few frames. DEFORM's recordings have no licence: they are
read from --data (github.com/roahmlab/DEFORM, folder data_set) and never copied.
"""
from __future__ import annotations

import argparse
import concurrent.futures
import math
import multiprocessing
import shlex
import sys
import time
from pathlib import Path

import numpy as np
import torch

from diffdlo.chain3d import deform, fit
from diffdlo.utils.files import check_fresh_out, out_lock, replacing, write_json_atomic

# DEFORM's paper (Chen et al., CoRL 2024), average L1 error over 5 s [cm] per cable 1..5; "frozen" was measured by
# issue 61's author (markers frozen at frame 1, the held ones driven).
PAPER_CM = {
    "frozen": (5.67, 5.29, 4.85, 5.30, 5.32),
    "XPBD": (4.00, 3.85, 3.80, 3.62, 4.35),
    "DER": (1.96, 1.91, 1.86, 1.50, 1.65),
    "Bi-LSTM": (1.98, 1.75, 1.10, 1.75, 1.88),
    "DEFORM": (1.01, 0.97, 0.77, 0.85, 0.99),
}
DEFORM_MS_PER_FRAME = 9.5     # the paper's DEFORM on a workstation CPU

FULL = dict(window=40, iterations=200, batch=8, lr=0.08, scan_points=9, bootstrap=3, bootstrap_iterations=40)
QUICK = dict(window=10, iterations=3, batch=2, lr=0.08, scan_points=3, bootstrap=2, bootstrap_iterations=2)


def _fit_one(data: str, cable: int, settings: dict, seed: int, threads: int, position: int, progress: bool
             ) -> fit.FitResult:
    """Load cable's train split and fit it (run in a worker process)."""
    torch.set_num_threads(threads)
    spec = deform.CABLES[cable]
    train = deform.load_split(data, cable, "train")
    return fit.fit_cable(train, deform.HELD_MARKERS, mass=spec.mass, length=spec.length, seed=seed,
                         progress=progress, desc=spec.name, **settings)


def fit_all(data: str, cables: list[int], settings: dict, seed: int, jobs: int, progress: bool,
            cost: dict[int, float] | None = None) -> dict[int, fit.FitResult]:
    """Every cable's fit, ``jobs`` at a time in spawned processes of one thread each (in this process for 1)."""
    if jobs <= 1 or len(cables) <= 1:
        before = torch.get_num_threads()
        try:
            return {c: _fit_one(data, c, settings, seed, 1, i, progress) for i, c in enumerate(cables)}
        finally:
            torch.set_num_threads(before)
    ctx = multiprocessing.get_context("spawn")
    with concurrent.futures.ProcessPoolExecutor(max_workers=jobs, mp_context=ctx) as pool:
        # the costliest first (a step's cost grows with the substeps the chain needs), so the jobs end together
        order = sorted(cables, key=lambda c: -cost.get(c, 0)) if cost else cables
        futures = {c: pool.submit(_fit_one, data, c, settings, seed, 1, i, progress) for i, c in enumerate(order)}
        return {c: futures[c].result() for c in cables}


def parameter_table(result: fit.FitResult) -> dict:
    out = {}
    for k in fit.FIT_NAMES:
        v, s = result.values[k], result.spread[k]
        out[k] = {"value": v, "unit": fit.UNITS[k], "spread_log": s, "factor": math.exp(s),
                  "low_68": v * math.exp(-s), "high_68": v * math.exp(s),
                  "bootstrap": [b[k] for b in result.bootstrap]}
    return out


def write_predictions(out: Path, cable: int, ids: list[str], pred: torch.Tensor) -> None:
    folder = out / "predictions" / f"DLO{cable}"
    folder.mkdir(parents=True, exist_ok=True)
    for i, key in enumerate(ids):
        with replacing(folder / f"{key}.npz", suffix=".npz") as tmp:
            with open(tmp, "wb") as f:
                np.savez_compressed(f, positions=pred[i].numpy().astype(np.float32))


def plot_errors(cables: dict, path: Path, label: str = "chain (fitted)",
                extra: tuple[str, str] | None = None) -> None:
    """The error over time per cable: ``cables[name]["ours"]`` as ``label`` (and ``extra``: (key, label) of a
    second result of the same cable, e.g. the physics-only one beside the residual's), the frozen baseline and the
    paper's DER and DEFORM means."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, len(cables), figsize=(3.2 * len(cables), 3.4), squeeze=False, sharey=True,
                             layout="constrained")
    for ax, (name, c) in zip(axes[0], cables.items()):
        t = [(2 + i) * deform.DT for i in range(len(c["ours"]["per_frame_m"]))]
        ax.plot(t, [100 * e for e in c["frozen"]["per_frame_m"]], color="grey", lw=1, label="frozen")
        if extra is not None:
            ax.plot(t, [100 * e for e in c[extra[0]]["per_frame_m"]], color="C4", lw=1, label=extra[1])
        ax.plot(t, [100 * e for e in c["ours"]["per_frame_m"]], color="C1", lw=1.2, label=label)
        k = int(name[3:]) - 1
        ax.axhline(PAPER_CM["DER"][k], color="C0", ls="--", lw=0.8, label="DER (paper, mean)")
        ax.axhline(PAPER_CM["DEFORM"][k], color="C2", ls=":", lw=0.8, label="DEFORM (paper, mean)")
        ax.set_title(f"{name}: {100 * c['ours']['l1_m']:.2f} cm")
        ax.set_xlabel("time [s]")
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("mean L1 error over eval files [cm]")
    handles, labels = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncol=len(labels), fontsize=8)     # below the panels
    with replacing(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=90)
    plt.close(fig)


def plot_shapes(name: str, key: str, recording: torch.Tensor, pred: torch.Tensor, path: Path,
                frames: tuple[int, ...] = (2, 100, 250, 499)) -> None:
    """Recorded (black) and predicted (orange) cable in 3-D, drawn in the same axes, at a few frames of one eval
    recording."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    T = recording.shape[0]
    frames = tuple(f for f in frames if 2 <= f < T) or (T - 1,)
    fig = plt.figure(figsize=(3.2 * len(frames), 3.4))
    both = torch.cat([recording[2:], pred]).reshape(-1, 3)
    lo, hi = both.min(0).values.numpy(), both.max(0).values.numpy()
    for j, f in enumerate(frames):
        ax = fig.add_subplot(1, len(frames), j + 1, projection="3d")
        r, p = recording[f].numpy(), pred[f - 2].numpy()
        ax.plot(r[:, 0], r[:, 1], r[:, 2], "o-", color="k", ms=3, lw=1, label="recorded")
        ax.plot(p[:, 0], p[:, 1], p[:, 2], "o-", color="C1", ms=3, lw=1, label="predicted")
        ax.set_xlim(lo[0], hi[0]); ax.set_ylim(lo[1], hi[1]); ax.set_zlim(0, max(hi[2], 0.1))
        err = 100 * float((pred[f - 2] - recording[f]).abs().mean())
        ax.set_title(f"t = {f * deform.DT:.2f} s, L1 {err:.1f} cm", fontsize=9)
        ax.tick_params(labelsize=6)
        if j == 0:
            ax.legend(fontsize=7, loc="upper left")
    fig.suptitle(f"{name}, eval recording {key}: open loop from frames 0-1", fontsize=10)
    fig.tight_layout()
    with replacing(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=90)
    plt.close(fig)


def table(cables: dict) -> str:
    head = ("| cable | ours [cm] | frozen [cm] (issue) | DER [cm] | DEFORM [cm] | ours, DEFORM's /500 [cm] | "
            "EI [N m^2] | EA [N] | drag [N s/m^2] | ms/frame (batched, alone) |")
    lines = [head, "|" + "|".join(["---"] * (head.count("|") - 1)) + "|"]
    for name, c in cables.items():
        k = int(name[3:]) - 1
        p = c["parameters"]
        lines.append(f"| {name} | {100 * c['ours']['l1_m']:.2f} | {100 * c['frozen']['l1_m']:.2f} "
                     f"({PAPER_CM['frozen'][k]:.2f}) | {PAPER_CM['DER'][k]:.2f} | {PAPER_CM['DEFORM'][k]:.2f} | "
                     f"{100 * c['ours']['deform_convention_m']:.2f} | "
                     f"{p['EI']['value']:.3g} (x/{p['EI']['factor']:.2f}) | "
                     f"{p['EA']['value']:.3g} | {p['drag']['value']:.3g} | {1e3 * c['ours']['time_per_frame_s']:.3f}, "
                     f"{1e3 * c['ours']['single_time_per_frame_s']:.3f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.real_cable", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True, help="DEFORM's data_set folder (or its checkout)")
    ap.add_argument("--out", required=True)
    ap.add_argument("--cables", nargs="+", type=int, default=sorted(deform.CABLES))
    ap.add_argument("--quick", action="store_true", help="a smoke run: a few tiny fit steps")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--jobs", type=int, default=1, help="fits run at once, one process of one thread each")
    ap.add_argument("--threads", type=int, default=2, help="torch threads of the evaluation (timed); default 2")
    ap.add_argument("--window", type=int, help=f"fit window [frames] (default {FULL['window']})")
    ap.add_argument("--iterations", type=int, help=f"Adam steps (default {FULL['iterations']})")
    ap.add_argument("--batch", type=int, help=f"windows per step (default {FULL['batch']})")
    ap.add_argument("--bootstrap", type=int, help=f"bootstrap refits (default {FULL['bootstrap']})")
    ap.add_argument("--bootstrap-iterations", type=int,
                    help=f"steps per refit (default {FULL['bootstrap_iterations']})")
    ap.add_argument("--no-progress", action="store_true")
    ap.add_argument("--overwrite", action="store_true")
    args = ap.parse_args(argv)
    data = Path(args.data)
    if not data.is_dir():
        ap.error(f"--data {args.data!r} is not a folder (give DEFORM's data_set folder)")
    bad = [c for c in args.cables if c not in deform.CABLES]
    if bad:
        ap.error(f"--cables {bad[0]!r} is not a DEFORM cable (one of {sorted(deform.CABLES)})")
    if len(set(args.cables)) != len(args.cables):
        ap.error(f"--cables {args.cables} names a cable twice")
    for flag, value, least in (("--jobs", args.jobs, 1), ("--threads", args.threads, 1), ("--window", args.window, 1),
                               ("--iterations", args.iterations, 0), ("--batch", args.batch, 1),
                               ("--bootstrap", args.bootstrap, 0),
                               ("--bootstrap-iterations", args.bootstrap_iterations, 0)):
        if value is not None and value < least:
            ap.error(f"{flag} must be at least {least}, got {value}")
    try:
        check_fresh_out(args.out, args.overwrite, "an earlier benchmark")
    except FileExistsError as exc:
        ap.error(str(exc))
    settings = dict(QUICK if args.quick else FULL)
    for key in ("window", "iterations", "batch", "bootstrap", "bootstrap_iterations"):
        if getattr(args, key) is not None:
            settings[key] = getattr(args, key)
    # every split is read (and checked) before any fitting starts
    try:
        splits = {c: (deform.load_split(data, c, "train"), deform.load_split(data, c, "eval")) for c in args.cables}
    except deform.RecordingError as exc:
        ap.error(str(exc))
    for c, (train, _) in splits.items():
        T = next(iter(train.values())).shape[0]
        if settings["window"] > T - 2:
            settings["window"] = max(1, T - 2)
    given = sys.argv[1:] if argv is None else argv
    command = "python -m benchmarks.real_cable " + " ".join(shlex.quote(a) for a in given)
    out = Path(args.out)
    t0 = time.perf_counter()
    with out_lock(out):
        cost = {c: fit.cable_model(train, mass=deform.CABLES[c].mass, length=deform.CABLES[c].length).substeps
                for c, (train, _) in splits.items()}
        fits = fit_all(str(data), args.cables, settings, args.seed, args.jobs, not args.no_progress, cost)
        fit_s = time.perf_counter() - t0
        torch.set_num_threads(args.threads)
        cables = {}
        for c in args.cables:
            name = deform.CABLES[c].name
            result = fits[c]
            evals = splits[c][1]
            ids = list(evals)
            ours, pred = fit.evaluate(result.model, result.values, evals, repeats=1 if args.quick else 3)
            frozen = fit.score(fit.frozen_prediction(evals, deform.HELD_MARKERS), evals)
            # one recording alone (no batching): the time per frame of a single cable, as DEFORM's is quoted
            first = {ids[0]: evals[ids[0]]}
            single, _ = fit.evaluate(result.model, result.values, first, repeats=1 if args.quick else 3)
            ours["single_time_per_frame_s"] = single["time_per_frame_s"]
            write_predictions(out, c, ids, pred)
            k = c - 1
            cables[name] = {
                "ours": ours, "frozen": frozen,
                "paper_cm": {m: v[k] for m, v in PAPER_CM.items()},
                "parameters": parameter_table(result),
                "fit": result.to_dict(),
                "cable": {"length_m": deform.CABLES[c].length, "mass_kg": deform.CABLES[c].mass,
                          "stiffness_rank": deform.CABLES[c].stiffness_rank},
                "eval_ids": ids,
            }
            try:
                plot_shapes(name, ids[0], evals[ids[0]], pred[0], out / "figures" / f"{name}_shapes.png")
            except ImportError:
                pass
        rank = sorted(cables, key=lambda n: cables[n]["parameters"]["EI"]["value"])
        paper_rank = sorted(cables, key=lambda n: cables[n]["cable"]["stiffness_rank"])
        summary = {"command": command, "settings": settings, "seed": args.seed, "jobs": args.jobs,
                   "eval_threads": args.threads, "fit_wall_s": fit_s, "wall_s": time.perf_counter() - t0,
                   "quick": args.quick, "deform_ms_per_frame": DEFORM_MS_PER_FRAME,
                   "EI_order_softest_first": rank, "paper_stiffness_order_softest_first": paper_rank,
                   "EI_orders_as_paper": rank == paper_rank, "cables": cables}
        write_json_atomic(out / "results.json", summary)
        try:
            plot_errors(cables, out / "figures" / "error_over_time.png")
        except ImportError:
            print("matplotlib is not installed (the plot extra): no figures", file=sys.stderr)
    print(table(cables))
    print(f"EI order (softest first): {rank}; the paper's stiffness order: {paper_rank}")
    print(f"fit {fit_s:.0f} s, total {time.perf_counter() - t0:.0f} s -> {out}/results.json")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
