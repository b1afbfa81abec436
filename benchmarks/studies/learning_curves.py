"""Learning curves of finished learner runs: success and moves per evaluation, across seeds, as a table and a picture.

    python -m benchmarks.studies.learning_curves runs/apg/tuned-50k-s0 runs/apg/tuned-50k-s1 --out docs/figures/apg_curves.png

Reads each run's ``eval.csv`` (step, success_rate, mean_length, mean_final_error: the run's deterministic evaluations;
a run's mean_length is over all its evaluation episodes, so it is the moves to success only where success is 1.0).
Prints, per evaluated step present in every run, the mean success across runs and its range, the mean episode
length and the mean final error; writes the figure (matplotlib, the ``plot`` extra) when ``--out`` is given.
"""
from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import numpy as np

from diffdlo.utils.files import replacing


def read_eval(run: Path) -> dict[int, dict[str, float]]:
    path = run / "eval.csv"
    if not path.is_file():
        raise SystemExit(f"learning_curves: {run} has no eval.csv (is it a finished learner run folder?)")
    with path.open() as f:
        rows = list(csv.DictReader(f))
    needed = {"step", "success_rate", "mean_length", "mean_final_error"}
    if not rows or not needed <= set(rows[0]):
        raise SystemExit(f"learning_curves: {path} lacks the columns {sorted(needed)}")
    return {int(float(r["step"])): {k: float(r[k]) for k in needed - {"step"}} for r in rows}


def curves(runs: list[Path]) -> tuple[list[int], dict[str, np.ndarray]]:
    """The steps every run evaluated at, and per column an array (runs, steps)."""
    evals = [read_eval(r) for r in runs]
    steps = sorted(set.intersection(*(set(e) for e in evals)))
    if not steps:
        raise SystemExit("learning_curves: the runs share no evaluated step")
    cols = ("success_rate", "mean_length", "mean_final_error")
    return steps, {c: np.array([[e[s][c] for s in steps] for e in evals]) for c in cols}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.studies.learning_curves", description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path, help="learner run folders (each with eval.csv)")
    ap.add_argument("--out", type=Path, default=None, help="write the figure here (png)")
    ap.add_argument("--title", default=None)
    ap.add_argument("--overwrite", action="store_true", help="replace an existing --out figure")
    args = ap.parse_args(argv)
    if args.out is not None and args.out.exists() and not args.overwrite:
        ap.error(f"--out {str(args.out)!r} already exists: choose another path or pass --overwrite to replace it")
    steps, c = curves(args.runs)
    print(f"{len(args.runs)} runs: {', '.join(str(r) for r in args.runs)}")
    print("| env steps | success (mean; min-max over runs) | episode length (mean; min-max) | final error [cm] |")
    print("|---|---|---|---|")
    for i, s in enumerate(steps):
        su, ln, fe = c["success_rate"][:, i], c["mean_length"][:, i], c["mean_final_error"][:, i] * 100
        print(f"| {s} | {su.mean():.2f}; {su.min():.2f}-{su.max():.2f} "
              f"| {ln.mean():.1f}; {ln.min():.1f}-{ln.max():.1f} "
              f"| {fe.mean():.2f} |")
    if args.out is not None:
        try:
            import matplotlib
            matplotlib.use("Agg")
            import matplotlib.pyplot as plt
        except ImportError:
            raise SystemExit("learning_curves: --out needs matplotlib (pip install -e '.[plot]')")
        fig, axes = plt.subplots(1, 2, figsize=(9, 3.4))
        for ax, key, label in ((axes[0], "success_rate", "success @1 cm"), (axes[1], "mean_length", "episode length")):
            v = c[key]
            ax.plot(steps, v.T, color="0.75", lw=0.8)
            ax.plot(steps, v.mean(0), color="C0", lw=2, label=f"mean of {len(args.runs)} runs")
            ax.set_xlabel("env steps (rope-moves simulated in training)")
            ax.set_ylabel(label)
            ax.grid(alpha=0.3)
        axes[0].legend(loc="lower right")
        if args.title:
            fig.suptitle(args.title)
        fig.tight_layout()
        with replacing(args.out, suffix=".png") as tmp:
            fig.savefig(tmp, dpi=110)
        print(f"figure -> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
