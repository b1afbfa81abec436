"""The report's figures (matplotlib, optional), drawn from the cells' records alone (no run folder): the summary
(success and moves against the simulator moves spent), per task the learners' success against env steps, the
planners' error against simulator evaluations, a gallery of start, final shape and target, the cost of planning
against learning, and the precision rows' success against the tolerance (those rows are in no other figure). Each
band is the mean +- the 95 % t-interval over seeds."""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from diffdlo.utils.files import replacing
from .costs import acting_sim_evals
from .grid import main_rows, row_label
from .precision import ladder_points, split_done
from .summary import heldout_source
from .stats import t_quantile


def figure_names(grid: dict[str, Any], done: list, costs: dict[str, list]) -> list[str]:
    """The files ``make_figures`` writes for these cells, in the report's order (known without drawing them, so the
    report's text does not depend on matplotlib being installed)."""
    tag = "quick_" if grid["name"] == "quick" else ""
    by_key = {_key(c): r for c, r in done}
    names = [f"{tag}summary.png"] if _summary_points(grid, by_key) else []
    if ladder_points(grid, by_key):
        names.append(f"{tag}precision.png")
    done, _ = split_done(grid, done)          # the task figures: the rows read at their own success
    for target in _targets(grid, done):
        if any(c["kind"] == "agent" and c["target"] == target and r.get("curve") for c, r in done):
            names.append(f"{tag}success_vs_steps_{target}.png")
        if any(c["kind"] == "planner" and c["target"] == target and r.get("sim_evals") for c, r in done):
            names.append(f"{tag}planner_error_vs_evals_{target}.png")
        if _gallery_panels(grid, done, target):
            names.append(f"{tag}gallery_{target}.png")
    names += [f"{tag}cost_{target}.png" for target in costs]
    return names


def _key(c: dict[str, Any]) -> tuple:
    return c["method"], c["variant"], c["target"], c["seed"]


def _targets(grid: dict[str, Any], done: list) -> list[str]:
    return [t for t in grid["targets"] if any(c["target"] == t for c, _ in done)
            or (t in grid.get("heldout", {}) and any(t in (r.get("heldout") or {}) for _, r in done))]


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


def _summary_points(grid: dict[str, Any], done: dict[tuple, dict], task: str = "random") -> list[dict[str, Any]]:
    """Per main row on ``task``: simulator moves spent for its evaluated episodes (training included), success and
    mean moves of the successful episodes."""
    points = []
    for image in (False, True):
        for method, variant in main_rows(grid, image):
            cells = [r for k, r in done.items() if k[:3] == (method, variant, task)]
            if not cells:
                continue
            eps = [e for r in cells for e in r["episodes"]]
            moves = float(np.mean([e["steps"] for e in eps]))
            if grid["methods"][method]["kind"] == "planner":
                spent = float(np.mean([r.get("sim_evals", 0) for r in cells])) + moves * len(cells[0]["episodes"])
            else:        # training (with backpropagated rope-moves and a teacher's rollouts) + acting (its rollouts)
                train = float(np.mean([r["env_steps"] + (r.get("sim_backward") or 0) + r.get("teacher_sim_evals", 0)
                                       for r in cells]))
                spent = train + moves * (1 + acting_sim_evals(cells)) * len(cells[0]["episodes"])
            succ = [e["steps"] for e in eps if e["success"]]
            points.append({"label": row_label(grid, method, variant) + ("" if not image else " [pictures]"),
                           "image": image, "spent": max(spent, 1.0), "success": len(succ) / len(eps),
                           "moves": float(np.mean(succ)) if succ else float("nan"), "seeds": len(cells)})
    return points


def _summary(plt, grid: dict[str, Any], done: dict[tuple, dict], note: str):
    points = _summary_points(grid, done)
    fig, axes = plt.subplots(1, 2, figsize=(10, 5.2))
    markers = "osD^v<>ph*"
    for i, p in enumerate(points):
        style = dict(marker=markers[i % len(markers)], ms=8, ls="none",
                     mfc="none" if p["image"] else None, label=f"{p['label']} ({p['seeds']} seeds)")
        axes[0].plot(p["spent"], 100 * p["success"], **style)
        axes[1].plot(p["spent"], p["moves"], **style)
    for ax, ylabel in ((axes[0], "success @1 cm [%]"), (axes[1], "moves to success (mean)")):
        ax.set_xscale("log")
        ax.set_xlabel("simulator moves spent per 20 episodes, training included")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
    axes[0].set_ylim(-5, 105)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, fontsize=7, loc="lower center", ncol=2, frameon=False)
    fig.suptitle("random targets: each main row (hollow: from 64 px pictures).\nPlanners: the moves they simulate "
                 "and execute; learners: training env steps + the moves they execute (and simulate, acting by "
                 f"rollouts){note}", fontsize=9)
    fig.subplots_adjust(bottom=0.32, top=0.9, wspace=0.25)
    return fig


def _precision(plt, points: list[dict[str, Any]], note: str):
    """Success against the mean-error tolerance, a panel per task, a line per precision row: filled markers exact,
    open ones lower bounds (some episodes ended at their own, looser success first), reached by a dotted line."""
    from matplotlib.lines import Line2D
    from matplotlib.ticker import NullFormatter

    tasks = list(dict.fromkeys(p["task"] for p in points))
    fig, axes = plt.subplots(1, len(tasks), figsize=(max(5.0 * len(tasks), 6.0), 4.4), squeeze=False, sharey=True)
    markers = "osD^v<>ph*"
    labels = list(dict.fromkeys(p["label"] for p in points))
    style = {label: dict(color=f"C{i % 10}", marker=markers[i % len(markers)]) for i, label in enumerate(labels)}
    for ax, task in zip(axes[0], tasks):
        for p in (p for p in points if p["task"] == task):
            x, y = 1000 * np.array(p["tols"]), 100 * np.array(p["success"])
            for i in range(len(x) - 1):                 # dotted into a lower bound: not a measured fall
                ax.plot(x[i:i + 2], y[i:i + 2], ls="-" if p["exact"][i + 1] else ":", lw=1,
                        color=style[p["label"]]["color"])
            for xi, yi, exact in zip(x, y, p["exact"]):
                ax.plot(xi, yi, ms=7, ls="none", mfc=None if exact else "none", **style[p["label"]])
        ticks = sorted({1000 * t for p in points for t in p["tols"]})
        ax.set_xscale("log")
        ax.set_xticks(ticks)
        ax.set_xticklabels([f"{t:g}" for t in ticks])
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.invert_xaxis()                               # tighter to the right
        ax.set_xlabel("tolerance of the mean error [mm]")
        ax.set_title(f"{task} ({', '.join(sorted({str(p['seeds']) for p in points if p['task'] == task}))} seeds)",
                     fontsize=9)
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("success [%]")
    axes[0][0].set_ylim(-5, 105)
    handles = [Line2D([], [], ms=7, lw=1, **style[label]) for label in labels]
    fig.legend(handles, labels, fontsize=7, loc="lower center", ncol=2, frameon=False)
    fig.suptitle("Precision rows: success against the tolerance of the mean error, the same episodes at each\n"
                 f"(open markers, dotted: lower bounds, some episodes ended at their own looser success first){note}",
                 fontsize=9)
    fig.subplots_adjust(bottom=0.1 + 0.06 * ((len(labels) + 1) // 2), top=0.84, wspace=0.08)
    return fig


def _success_vs_steps(plt, done: list, target: str, note: str):
    """Evaluation success against env steps (each record's curve), all learners on one task."""
    by: dict[tuple, list] = {}
    for c, r in done:
        if c["kind"] == "agent" and c["target"] == target and r.get("curve"):
            by.setdefault((c["method"], c["variant"]), []).append(np.array(r["curve"], dtype=float))
    fig, ax = plt.subplots(figsize=(5.5, 3.5))
    for (method, variant), curves in by.items():
        x = curves[0][:, 0]
        ys = np.stack([np.interp(x, c[:, 0], c[:, 1]) for c in curves])
        _band(ax, x, ys, f"{method}/{variant}", clip=(0.0, 1.0))
    ax.set_xscale("log")
    ax.set_xlabel("env steps")
    ax.set_ylabel("eval success @1 cm")
    ax.set_title(f"{target}: success vs env steps{note}", fontsize=9)
    ax.legend(fontsize=7)
    return fig


def _planner_error_vs_evals(plt, done: list, target: str, note: str):
    """Planners' mean per-move error against simulator evaluations (x = move k x sim evals per move)."""
    by: dict[tuple, list] = {}
    for c, r in done:
        if c["kind"] == "planner" and c["target"] == target and r.get("sim_evals"):
            by.setdefault((c["method"], c["variant"]), []).append(r)
    fig, ax = plt.subplots(figsize=(5.5, 3.5))
    for (method, variant), runs in by.items():
        curves, per_move = [], []
        for res in runs:
            eps = [e for e in res["episodes"] if e.get("errors")]
            if not eps:
                continue
            n = max(len(e["errors"]) for e in eps)
            errs = np.array([e["errors"] + [e["errors"][-1]] * (n - len(e["errors"])) for e in eps])
            curves.append(errs.mean(0))
            per_move.append(res["sim_evals"] / max(res["env_steps"], 1))
        if not curves:
            continue
        n = min(len(c) for c in curves)
        epm = float(np.mean(per_move))
        _band(ax, np.arange(n) * epm, np.stack([c[:n] for c in curves]) * 100,
              label=f"{method}/{variant} ({epm:.0f} evals/move)")
    ax.axhline(1.0, color="k", lw=0.6, ls="--")
    ax.axhline(2.0, color="k", lw=0.6, ls=":")
    ax.set_xlabel("simulator evaluations (rope-moves)")
    ax.set_ylabel("mean shape error [cm]")
    ax.set_title(f"{target}: planners' error vs sim evals{note}", fontsize=9)
    ax.legend(fontsize=7)
    return fig


NO_SHAPES = "no shapes"     # a gallery entry: the cell ran, its record holds no shapes


def _gallery_panels(grid: dict[str, Any], done: list, target: str) -> list[tuple[str, list]]:
    """Per row on ``target`` (a method per row, ordered as the grid; where the grid names its main rows, those only,
    a learner on a held-out shape by its policy trained on the main ``heldout_trained_on`` task): its seeds' first
    episodes' shapes. A seed's entry is the shapes, NO_SHAPES where the cell ran without recording them (cells
    collected before the records held shapes), or None where it has not run."""
    main = grid.get("main") or {}
    keep = set(main_rows(grid)) | set(main_rows(grid, image=True)) if main else None
    trained_on = heldout_source(grid) if main else None
    rows: dict[tuple, dict[int, Any]] = {}
    for c, r in done:
        if keep is not None and (c["method"], c["variant"]) not in keep:
            continue
        if c["target"] == target:
            rows.setdefault((c["method"], c["variant"], ""), {})[c["seed"]] = r.get("shapes") or NO_SHAPES
        held = (r.get("heldout") or {}).get(target)
        if held and c["target"] != target and (trained_on is None or c["target"] == trained_on):
            rows.setdefault((c["method"], c["variant"], c["target"]), {})[c["seed"]] = \
                held.get("shapes") or NO_SHAPES
    order = list(grid["methods"])
    out = []
    for (method, variant, trained), by_seed in sorted(rows.items(), key=lambda kv: (
            order.index(kv[0][0]) if kv[0][0] in order else 99, kv[0][1], kv[0][2])):
        if all(v == NO_SHAPES for v in by_seed.values()):
            continue
        label = f"{method}/{variant}" + (f"\n(trained on {trained})" if trained else "")
        out.append((label, [by_seed.get(s) for s in grid["seeds"]]))
    return out


def final_errors(final: np.ndarray, target: np.ndarray) -> str:
    """A gallery panel's caption: the mean and the worst node's error [mm] of a final shape against its target,
    centroids aligned as the task's errors (diffdlo.rewards.node_errors)."""
    node = np.linalg.norm((final - final.mean(0)) - (target - target.mean(0)), axis=1)
    return f"{node.mean() * 1e3:.1f} / {node.max() * 1e3:.1f} mm"


def _gallery(plt, grid: dict[str, Any], done: list, target: str, note: str):
    """Start (grey), final shape (blue) and target (dashed, at the final shape's centroid: the error ignores
    translation) of each seed's first episode, with its final mean and worst node error (``final_errors``), a row
    per method; every panel the same view and scale, and the same
    episode in each column (the episodes are paired) around that column's centre. The view holds 98 % of the drawn
    points, so one rope that drifted off does not shrink every other to a sliver; what lies beyond it is cut at the
    panel's edge."""
    def placed(sh):
        """(start, final, target moved onto the final shape's centroid) of one episode's shapes."""
        final, tgt = np.array(sh["final"]), np.array(sh["target"])
        return np.array(sh["start"]), final, tgt - tgt.mean(0) + final.mean(0)

    panels = _gallery_panels(grid, done, target)
    seeds = list(grid["seeds"])
    rows = [(label, [sh if sh is None or isinstance(sh, str) else placed(sh) for sh in row])
            for label, row in panels]
    # A column's panels share its centre (one episode, the same start shape): the median of its panels' middles, so
    # a rope that drifted off does not move it; every panel shares one half-width.
    columns = [[p for _, row in rows if isinstance(p := row[j], tuple)] for j in range(len(seeds))]

    def middle(p):
        pts = np.concatenate(p)
        return (pts.min(0) + pts.max(0)) / 2
    centres = [np.median([middle(p) for p in col], axis=0) if col else np.zeros(2) for col in columns]
    drawn = np.concatenate([np.abs(a - centres[j]).max(1) for j, col in enumerate(columns) for p in col for a in p])
    lim = max(float(np.quantile(drawn, 0.98)), 0.1) * 1.05
    cut = bool((drawn > lim).any())
    height = 1.9 * len(rows) + 0.8
    fig, axes = plt.subplots(len(rows), len(seeds), figsize=(1.9 * len(seeds) + 1.8, height), squeeze=False)
    for i, (label, row) in enumerate(rows):
        for j, shapes in enumerate(row):
            ax = axes[i, j]
            ax.set_xlim(centres[j][0] - lim, centres[j][0] + lim)
            ax.set_ylim(centres[j][1] - lim, centres[j][1] + lim)
            ax.set_aspect("equal")
            ax.set_xticks([])
            ax.set_yticks([])
            if i == 0:
                ax.set_title(f"seed {seeds[j]}, episode 0", fontsize=7)
            if not isinstance(shapes, tuple):
                ax.text(*centres[j], "not run" if shapes is None else "ran; shapes\nnot recorded", ha="center",
                        va="center", fontsize=7, color="0.5")
                continue
            start, final, tgt = shapes
            ax.plot(*start.T, color="0.7", lw=1)
            ax.plot(*tgt.T, "k--", lw=1)
            ax.plot(*final.T, color="tab:blue", lw=1.5)
            ax.text(0.03, 0.03, final_errors(final, tgt), transform=ax.transAxes, fontsize=6, color="0.3")
        axes[i, 0].set_ylabel(label, fontsize=7, rotation=0, ha="right", va="center")
    fig.suptitle(f"{target}: start (grey), final shape (blue), target (dashed; at the final shape's centroid); "
                 f"final error, mean / worst node [mm]\nview ±{lim:.2f} m in every panel (a column: one episode, one "
                 f"centre)"
                 + ("; shapes beyond it are cut" if cut else "") + note, fontsize=8)
    fig.subplots_adjust(top=1 - 0.75 / height, bottom=0.2 / height, left=0.2, right=0.98)
    return fig


def _pyplot():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(plt, fig, path: Path, dpi: int = 60) -> Path:
    if not fig.legends:                                        # a figure legend has its place already
        title = fig.get_suptitle() if hasattr(fig, "get_suptitle") else ""
        fig.tight_layout(rect=(0, 0, 1, 1 - 0.3 / fig.get_figheight()) if title else None)   # the title's band kept
    with replacing(path, suffix=path.suffix) as tmp:          # a reader never sees half a picture
        fig.savefig(tmp, dpi=dpi, format=path.suffix.lstrip(".") or None, metadata={"Software": None})
    plt.close(fig)
    return path


def make_figures(grid: dict[str, Any], done: list, figdir: Path) -> list[Path]:
    """The summary and, per task, the learners' success curves, the planners' error against simulator evaluations
    and the gallery, from the finished cells ``done`` ([(cell, record)]). Returns the files written."""
    plt = _pyplot()
    figdir.mkdir(parents=True, exist_ok=True)
    tag = "quick_" if grid["name"] == "quick" else ""
    note = " [QUICK RUN: format only]" if tag else ""
    written: list[Path] = []
    by_key = {_key(c): r for c, r in done}
    if _summary_points(grid, by_key):
        written.append(_save(plt, _summary(plt, grid, by_key, note), figdir / f"{tag}summary.png", dpi=80))
    points = ladder_points(grid, by_key)
    if points:
        written.append(_save(plt, _precision(plt, points, note), figdir / f"{tag}precision.png", dpi=80))
    done, _ = split_done(grid, done)          # the task figures: the rows read at their own success
    for target in _targets(grid, done):
        if any(c["kind"] == "agent" and c["target"] == target and r.get("curve") for c, r in done):
            written.append(_save(plt, _success_vs_steps(plt, done, target, note),
                                 figdir / f"{tag}success_vs_steps_{target}.png"))
        if any(c["kind"] == "planner" and c["target"] == target and r.get("sim_evals") for c, r in done):
            written.append(_save(plt, _planner_error_vs_evals(plt, done, target, note),
                                 figdir / f"{tag}planner_error_vs_evals_{target}.png"))
        if _gallery_panels(grid, done, target):
            written.append(_save(plt, _gallery(plt, grid, done, target, note), figdir / f"{tag}gallery_{target}.png",
                                 dpi=70))
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
