"""Learning curves from the CSV logs of agents.sac / agents.ppo runs (the thesis's Chapter 4 figures).

    python -m agents.tools.plot --runs runs/sac-points runs/sac-image --out curves.png [--smooth 5]

One panel per curve: eval success rate, eval mean reward, eval episode length, rollout reward, rollout episode
length, actor loss, critic loss, entropy coefficient (SAC) / policy entropy (PPO); one line per run (its directory
name), raw values faint and a running mean on top (as the thesis's red running average).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from agents.common.logs import read_csv

PANELS = [("eval", "success_rate", "eval success rate"), ("eval", "mean_reward", "eval mean reward"),
          ("eval", "mean_length", "eval episode length"), ("rollout", "ep_reward", "rollout mean reward"),
          ("rollout", "ep_length", "rollout episode length"), ("train", "actor_loss", "actor loss"),
          ("train", "critic_loss", "critic loss"), ("train", "ent_coef", "entropy coefficient"),
          ("train", "entropy", "policy entropy")]


def running_mean(y: np.ndarray, k: int) -> np.ndarray:
    if k <= 1 or len(y) < 2:
        return y
    c = np.cumsum(np.insert(y, 0, 0.0))
    out = np.empty_like(y)
    for i in range(len(y)):
        lo = max(0, i - k + 1)
        out[i] = (c[i + 1] - c[lo]) / (i + 1 - lo)
    return out


def plot_runs(runs: list[Path], out: Path, smooth: int = 5) -> Path:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    data = {}
    for run in runs:
        run = Path(run)
        if not run.is_dir():
            raise FileNotFoundError(f"no run directory {run}")
        data[run.name or str(run)] = {g: read_csv(run / f"{g}.csv") for g in ("eval", "rollout", "train")
                                      if (run / f"{g}.csv").exists()}
    if not any(data.values()):
        raise FileNotFoundError(f"no eval/rollout/train CSV in {[str(r) for r in runs]}")
    panels = [p for p in PANELS if any(rows.get(p[0]) and p[1] in rows[p[0]][0] for rows in data.values())]
    cols = 3
    nrows = (len(panels) + cols - 1) // cols
    fig, axes = plt.subplots(nrows, cols, figsize=(4.5 * cols, 3.2 * nrows), squeeze=False)
    for ax, (group, key, title) in zip(axes.flat, panels):
        for i, (name, rows) in enumerate(data.items()):
            r = [row for row in rows.get(group, []) if row.get(key) not in (None, "")]
            if not r:
                continue
            x = np.array([float(row["step"]) for row in r])
            y = np.array([float(row[key]) for row in r])
            color = f"C{i}"
            marker = "o" if len(x) < 30 else None        # a short run still shows its few points
            ax.plot(x, y, color=color, alpha=0.3, lw=0.8)
            ax.plot(x, running_mean(y, smooth), color=color, lw=1.6, label=name, marker=marker, ms=3)
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("env steps")
        ax.grid(alpha=0.3)
    for ax in list(axes.flat)[len(panels):]:
        ax.axis("off")
    axes.flat[0].legend(fontsize=8)
    fig.tight_layout()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m agents.tools.plot", description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", nargs="+", required=True, help="run directories (each with eval/rollout/train.csv)")
    ap.add_argument("--out", required=True, help="figure path (.png)")
    ap.add_argument("--smooth", type=int, default=5, help="running-mean window (points)")
    args = ap.parse_args(argv)
    try:
        path = plot_runs([Path(r) for r in args.runs], Path(args.out), args.smooth)
    except FileNotFoundError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
