"""The report's figures (matplotlib, optional): learning curves, success against env steps, planners' error against
simulator evaluations, a gallery of final shapes, and the cost of planning against learning. Each band is the mean
+- the 95 % t-interval over seeds."""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from diffdlo.files import replacing
from .grid import cell_dir
from .stats import t_quantile

CURVES = [("eval", "mean_reward", "eval mean reward"), ("eval", "mean_length", "eval episode length"),
          ("rollout", "ep_reward", "rollout mean reward"), ("rollout", "ep_length", "rollout episode length"),
          ("train", "actor_loss", "actor loss"), ("train", "critic_loss", "critic loss"),
          ("train", "loss", "world-model loss (PlaNet)")]


def _series(dirs: list[Path], group: str, key: str):
    """Per-seed (step, value) series of one CSV column, interpolated onto the first seed's steps."""
    from agents.logs import read_csv

    runs = []
    for d in dirs:
        p = d / f"{group}.csv"
        if not p.exists():
            continue
        rows = [r for r in read_csv(p) if r.get(key) not in (None, "")]
        if rows:
            runs.append((np.array([float(r["step"]) for r in rows]), np.array([float(r[key]) for r in rows])))
    if not runs:
        return None
    x = runs[0][0]
    ys = np.stack([np.interp(x, sx, sy) for sx, sy in runs])
    return x, ys


def _band(ax, x, ys, label, clip: tuple[float, float] | None = None):
    """The mean of ``ys`` (seeds x points) over ``x`` with its t-interval band (none for one seed)."""
    m = ys.mean(0)
    line, = ax.plot(x, m, marker=".", ms=3, label=f"{label} (n={len(ys)})")
    if len(ys) > 1:
        half = t_quantile(0.975, len(ys) - 1) * ys.std(0, ddof=1) / math.sqrt(len(ys))
        lo, hi = m - half, m + half
        if clip is not None:                       # as the table's intervals: a rate's band stays in [0, 1]
            lo, hi = np.clip(lo, *clip), np.clip(hi, *clip)
        ax.fill_between(x, lo, hi, color=line.get_color(), alpha=0.2)




def _learner_curves(plt, by: dict[tuple, list[Path]], method: str, target: str, note: str):
    """A learner's training curves on one task, one line per variant (points vs images, rewards); None if none."""
    keys = [k for k in by if k[0] == "agent" and k[1] == method and k[3] == target]
    panels = [(g, key, title) for g, key, title in CURVES if any(_series(by[k], g, key) is not None for k in keys)]
    if not panels:
        return None
    fig, axes = plt.subplots(2, 3, figsize=(11, 5.5), squeeze=False)
    for ax, (g, key, title) in zip(axes.flat, panels[:6]):
        for k in keys:
            s = _series(by[k], g, key)
            if s is not None:
                _band(ax, *s, label=k[2])
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("env steps", fontsize=8)
        ax.legend(fontsize=7)
    for ax in list(axes.flat)[len(panels[:6]):]:
        ax.axis("off")
    fig.suptitle(f"{method} on {target}: mean ± 95% t-CI over seeds{note}", fontsize=10)
    return fig


def _success_vs_steps(plt, by: dict[tuple, list[Path]], target: str, note: str):
    """Evaluation success against env steps, all learners on one task; None without learners."""
    keys = [k for k in by if k[0] == "agent" and k[3] == target]
    if not keys:
        return None
    fig, ax = plt.subplots(figsize=(5.5, 3.5))
    for k in keys:
        s = _series(by[k], "eval", "success_rate")
        if s is not None:
            _band(ax, *s, label=f"{k[1]}/{k[2]}", clip=(0.0, 1.0))
    ax.set_xlabel("env steps")
    ax.set_ylabel("eval success @1 cm")
    ax.set_title(f"{target}: success vs env steps{note}", fontsize=9)
    ax.legend(fontsize=7)
    return fig


def _planner_error_vs_evals(plt, by: dict[tuple, list[Path]], target: str, note: str):
    """Planners' mean per-move error against simulator evaluations (x = move k x sim evals per move); None unless a
    planner that simulates ran on the task."""
    keys = [k for k in by if k[0] == "planner" and k[3] == target]
    if not any(k[1] != "greedy" for k in keys):
        return None
    fig, ax = plt.subplots(figsize=(5.5, 3.5))
    for k in keys:
        curves, per_move = [], []
        for d in by[k]:
            res = json.loads((d / "results.json").read_text())
            eps = res["episodes"]
            n = max(len(e["errors"]) for e in eps)
            errs = np.array([e["errors"] + [e["errors"][-1]] * (n - len(e["errors"])) for e in eps])
            curves.append(errs.mean(0))
            per_move.append(res["sim_evals"] / max(res["env_steps"], 1))
        n = min(len(c) for c in curves)
        ys = np.stack([c[:n] for c in curves]) * 100
        epm = float(np.mean(per_move))
        if epm == 0:   # greedy simulates nothing
            continue
        _band(ax, np.arange(n) * epm, ys, label=f"{k[1]} ({epm:.0f} evals/move)")
    ax.axhline(1.0, color="k", lw=0.6, ls="--")
    ax.axhline(2.0, color="k", lw=0.6, ls=":")
    ax.set_xlabel("simulator evaluations (rope-moves)")
    ax.set_ylabel("mean shape error [cm]")
    ax.set_title(f"{target}: planners' error vs sim evals{note}", fontsize=9)
    ax.legend(fontsize=7)
    return fig


def _gallery(plt, grid: dict[str, Any], by: dict[tuple, list[Path]], target: str, note: str):
    """The final-shape pictures each entry point drew with diffdlo.render.plot_ropes (first seed); None if none."""
    pics = []
    for k in sorted((k for k in by if k[3] == target), key=lambda k: list(grid["methods"]).index(k[1])):
        d = sorted(by[k])[0]
        for name in ("shapes.png", "eval_episodes.png", "ep0/shapes.png"):
            if (d / name).exists():
                pics.append((f"{k[1]}/{k[2]} ({d.name})", d / name))
                break
    if not pics:
        return None
    cols = min(3, len(pics))
    rows = (len(pics) + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(4 * cols, 3.2 * rows), squeeze=False)
    for ax in axes.flat:
        ax.axis("off")
    for ax, (title, path) in zip(axes.flat, pics):
        ax.imshow(plt.imread(path))
        ax.set_title(title, fontsize=8)
    fig.suptitle(f"{target}: start and final shapes against the target (dashed), first seed{note}", fontsize=10)
    return fig


def _pyplot():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(plt, fig, path: Path, dpi: int = 60) -> Path:
    fig.tight_layout()
    with replacing(path, suffix=path.suffix) as tmp:          # a reader never sees half a picture
        fig.savefig(tmp, dpi=dpi, format=path.suffix.lstrip(".") or None)
    plt.close(fig)
    return path


def make_figures(grid: dict[str, Any], done: list, figdir: Path) -> list[Path]:
    """Per task, the learners' curves, their success against env steps, the planners' error against simulator
    evaluations and the gallery, from the finished cells ``done`` ([(cell, results)]). Returns the files written."""
    plt = _pyplot()
    figdir.mkdir(parents=True, exist_ok=True)
    tag = "quick_" if grid["name"] == "quick" else ""
    note = " [QUICK RUN: format only]" if tag else ""
    by: dict[tuple, list[Path]] = {}
    for c, r in done:
        by.setdefault((c["kind"], c["method"], c["variant"], c["target"]), []).append(cell_dir(c))
    written: list[Path] = []
    for target in sorted({k[3] for k in by}, key=lambda t: grid["targets"].index(t)):
        figs = [(_learner_curves(plt, by, method, target, note), f"curves_{method}_{target}")
                for method, spec in grid["methods"].items() if spec["kind"] == "agent"]
        figs += [(_success_vs_steps(plt, by, target, note), f"success_vs_steps_{target}"),
                 (_planner_error_vs_evals(plt, by, target, note), f"planner_error_vs_evals_{target}")]
        written += [_save(plt, fig, figdir / f"{tag}{name}.png") for fig, name in figs if fig is not None]
        gallery = _gallery(plt, grid, by, target, note)
        if gallery is not None:
            written.append(_save(plt, gallery, figdir / f"{tag}gallery_{target}.png", dpi=70))
    return written


def make_cost_figures(grid: dict[str, Any], costs: dict[str, list[dict[str, Any]]], figdir: Path) -> list[Path]:
    """Per task: cumulative simulator moves and wall seconds against episodes solved, planners and learners on the
    same axes (a learner starts at its training cost; where its line crosses CEM's it has paid back)."""
    plt = _pyplot()
    figdir.mkdir(parents=True, exist_ok=True)
    tag = "quick_" if grid["name"] == "quick" else ""
    written = []
    episodes = np.logspace(0, 4, 60)
    for target, rows in costs.items():
        fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
        for ax, key, unit in ((axes[0], "moves", "simulator moves"), (axes[1], "s", "wall seconds")):
            for r in rows:
                if math.isnan(r[f"episode_{key}"]):
                    continue
                label = f"{r['method']}/{r['variant']}" + ("" if r["trained_on"] == target else f" ({r['trained_on']})")
                ax.plot(episodes, r[f"train_{key}"] + episodes * r[f"episode_{key}"],
                        label=f"{label}: {r['success']:.0%}")
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_xlabel("episodes run")
            ax.set_ylabel(f"cumulative {unit}")
            ax.legend(fontsize=6)
        fig.suptitle(f"{target}: cost of planning vs learning (legend: success @1 cm)"
                     + (" [QUICK RUN: format only]" if tag else ""), fontsize=9)
        written.append(_save(plt, fig, figdir / f"{tag}cost_{target}.png"))
    return written
