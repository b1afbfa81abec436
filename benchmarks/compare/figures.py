"""The report's figures (matplotlib, optional), drawn from the cells' records alone (no run folder): the summary
(success and moves against the simulator moves spent), per task the learners' success against env steps, the
planners' error against simulator evaluations, a gallery of start, final shape and target, the cost of planning
against learning, and the precision rows' success against the tolerance (those rows are in no other figure). Each
band is the mean +- the 95 % t-interval over seeds.

Each figure is laid out to be read at the size it is written (``DPI``: the line plots 800 to 1,100 px wide): a
constrained layout, legends outside the axes (beside or below them, the room made for them), rows named by their
short names or method/variant keys (the full names: the report's methods), a colour per method and a line style per
variant. tests/test_figures_legible.py checks that no text or legend is cut or covers a panel."""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Callable

import numpy as np

from diffdlo.utils.files import replacing
from .costs import acting_sim_evals
from .grid import learner_source, main_rows, route_targets
from .precision import ladder_points, short_label, split_done
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


LINESTYLES = ("-", "--", ":", "-.", (0, (6, 1.5, 1, 1.5, 1, 1.5)), (0, (10, 3)), (0, (1, 3)))
MARKERS = "osD^v<>ph*"


def _second_line(note: str) -> str:
    """A title's note (" [QUICK RUN: format only]") on a line of its own, so the title stays within its panel."""
    return f"\n{note.strip()}" if note else ""


def _row_styles(keys: list[tuple[str, str]]) -> dict[tuple[str, str], dict[str, Any]]:
    """A line style per (method, variant): a colour per method (in the order first met), and within a method a line
    style and marker per variant, so that no two rows of a legend look alike (matplotlib's cycle repeats after 10)."""
    methods: dict[str, list[str]] = {}
    for method, variant in keys:
        if variant not in methods.setdefault(method, []):
            methods[method].append(variant)
    styles = {}
    for i, (method, variants) in enumerate(methods.items()):
        for j, variant in enumerate(variants):
            styles[(method, variant)] = dict(color=f"C{i % 10}", ls=LINESTYLES[(j + i // 10) % len(LINESTYLES)],
                                             marker=MARKERS[j % len(MARKERS)])
    return styles


def _band(ax, x, ys, label, clip: tuple[float, float] | None = None, style: dict[str, Any] | None = None):
    """The mean of ``ys`` (seeds x points) over ``x`` with its t-interval band (none for one seed)."""
    m = ys.mean(0)
    line, = ax.plot(x, m, ms=3, label=label, **(style or {"marker": "."}))
    if len(ys) > 1:
        half = t_quantile(0.975, len(ys) - 1) * ys.std(0, ddof=1) / math.sqrt(len(ys))
        lo, hi = m - half, m + half
        if clip is not None:                       # as the table's intervals: a rate's band stays in [0, 1]
            lo, hi = np.clip(lo, *clip), np.clip(hi, *clip)
        ax.fill_between(x, lo, hi, color=line.get_color(), alpha=0.15)


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
            points.append({"label": short_label(grid, method, variant), "method": method, "variant": variant,
                           "image": image, "spent": max(spent, 1.0), "success": len(succ) / len(eps),
                           "moves": float(np.mean(succ)) if succ else float("nan"), "seeds": len(cells)})
    return points


def _summary(plt, grid: dict[str, Any], done: dict[tuple, dict], note: str):
    """Success and moves against the simulator moves spent, a marker per main row on random targets: a colour per
    method, hollow where the row plans or acts from pictures (beside its method's first row, same colour and
    marker); the legend below the panels, by the rows' short names (their full names: the report's methods)."""
    points = _summary_points(grid, done)
    colours = {m: f"C{i % 10}" for i, m in enumerate(dict.fromkeys(p["method"] for p in points))}
    marker_of: dict[tuple[str, str], str] = {}
    first_row: dict[str, str] = {}
    for p in points:
        if not p["image"]:
            marker_of[(p["method"], p["variant"])] = MARKERS[len(marker_of) % len(MARKERS)]
            first_row.setdefault(p["method"], marker_of[(p["method"], p["variant"])])
    n_seeds = len(grid["seeds"])
    fig, axes = plt.subplots(1, 2, figsize=(11, 5.6), layout="constrained")
    for p in points:
        marker = marker_of.get((p["method"], p["variant"])) or first_row.get(p["method"], "X")
        seeds = "" if p["seeds"] == n_seeds else f" ({p['seeds']} seeds)"
        style = dict(marker=marker, ms=9, ls="none", color=colours[p["method"]], mew=1.5,
                     mfc="none" if p["image"] else None,
                     label=p["label"] + (" (pictures)" if p["image"] else "") + seeds)
        axes[0].plot(p["spent"], 100 * p["success"], **style)
        axes[1].plot(p["spent"], p["moves"], **style)
    episodes = grid.get("episodes", 20)
    for ax, ylabel in ((axes[0], "success at 1 cm [%]"), (axes[1], "moves to success (mean)")):
        ax.set_xscale("log")
        ax.set_xlabel(f"simulator moves spent per {episodes} episodes\n(training included)")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
    axes[0].set_ylim(-5, 105)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, fontsize=9, loc="outside lower center", ncol=4, frameon=False)
    fig.suptitle(f"Random targets, the main rows ({n_seeds} seeds each unless named; hollow: from 64 px pictures)"
                 f"{note}\nplanners: the moves they simulate and execute; learners: training env steps + the moves "
                 "they execute (and simulate, when acting by rollouts)", fontsize=10)
    return fig


def _precision(plt, points: list[dict[str, Any]], note: str):
    """Success against the mean-error tolerance, a panel per task, a line per precision row (its markers moved a
    little sideways, so rows at the same success stay visible). A filled marker: these episodes' exact success; a
    filled one with a black edge, reached by a dashed line: where these episodes give only a lower bound, the
    tolerance ladder's measured success on the same cells (``ladder_points``'s ``measured``); an open marker with an
    upward arrow and "≥": a lower bound nothing measured, with no line into it (not a measured fall)."""
    from matplotlib.lines import Line2D
    from matplotlib.ticker import NullFormatter

    tasks = list(dict.fromkeys(p["task"] for p in points))
    fig, axes = plt.subplots(1, len(tasks), figsize=(4.6 * len(tasks) + 1.4, 5.2), squeeze=False, sharey=True,
                             layout="constrained")
    labels = list(dict.fromkeys(p["label"] for p in points))
    style = {label: dict(color=f"C{i % 10}", marker=MARKERS[i % len(MARKERS)]) for i, label in enumerate(labels)}
    dodge = {label: 10 ** (0.035 * (i - (len(labels) - 1) / 2)) for i, label in enumerate(labels)}
    ticks = sorted({1000 * t for p in points for t in p["tols"]})
    kinds_drawn: set[str] = set()
    for ax, task in zip(axes[0], tasks):
        for p in (p for p in points if p["task"] == task):
            st = style[p["label"]]
            measured = p.get("measured") or [None] * len(p["tols"])
            kind = ["exact" if ok else "bound" if m is None else "ladder" for ok, m in zip(p["exact"], measured)]
            x = 1000 * np.array(p["tols"]) * dodge[p["label"]]
            y = 100 * np.array([s if m is None else m for s, m in zip(p["success"], measured)])
            for i in range(len(x) - 1):
                if "bound" in kind[i:i + 2]:            # no line into a lower bound: it is not a measured fall
                    continue
                ax.plot(x[i:i + 2], y[i:i + 2], ls="-" if kind[i:i + 2] == ["exact"] * 2 else "--", lw=1.2,
                        color=st["color"])
            for xi, yi, k in zip(x, y, kind):
                kinds_drawn.add(k)
                if k == "exact":
                    ax.plot(xi, yi, ms=7, ls="none", **st)
                elif k == "ladder":
                    ax.plot(xi, yi, ms=8, ls="none", mec="k", mew=1.5, **st)
                else:
                    ax.plot(xi, yi, ms=8, ls="none", mfc="none", mew=1.5, **st)
                    ax.annotate(f"≥ {yi:.0f} %", xy=(xi, yi), xytext=(0, 30), textcoords="offset points",
                                ha="center", va="bottom", fontsize=9, color=st["color"],
                                arrowprops=dict(arrowstyle="<|-", color=st["color"], lw=1.2, shrinkA=0, shrinkB=5))
        ax.set_xscale("log")
        ax.set_xlim(max(ticks) * 1.35, min(ticks) / 1.35)    # inverted: tighter to the right
        ax.set_xticks(ticks)
        ax.set_xticklabels([f"{t:g}" for t in ticks])
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_xlabel("tolerance of the mean error [mm]")
        seeds = ", ".join(sorted({str(p["seeds"]) for p in points if p["task"] == task}))
        ax.set_title(f"{task} ({seeds} seeds)", fontsize=10)
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("success [%]")
    axes[0][0].set_ylim(-5, 112)
    handles = [Line2D([], [], ms=7, lw=1.2, **style[label]) for label in labels]
    grey = dict(color="0.45", marker="o", ms=7)
    kinds = [("exact", Line2D([], [], ls="-", lw=1.2, **grey), "exact: these episodes"),
             ("ladder", Line2D([], [], ls="--", lw=1.2, mec="k", mew=1.5, **grey),
              "measured by the tolerance ladder:\nthe cells re-evaluated until 2 mm"),
             ("bound", Line2D([], [], ls="none", mfc="none", mew=1.5, **grey),
              "≥ a lower bound: episodes ended at\ntheir own, looser success first")]
    kinds = [(h, text) for k, h, text in kinds if k in kinds_drawn]
    per_column = max(len(kinds), 3)             # the rows in columns, then a column of what the markers mean
    blank = -len(labels) % per_column
    handles += [Line2D([], [], ls="none")] * blank + [h for h, _ in kinds]
    texts = labels + [""] * blank + [text for _, text in kinds]
    fig.legend(handles, texts, fontsize=9, loc="outside lower center", frameon=False,
               ncol=math.ceil(len(handles) / per_column))
    fig.suptitle("Precision rows: success against the tolerance of the mean error" + _second_line(note), fontsize=11)
    return fig


def _success_vs_steps(plt, done: list, target: str, note: str):
    """Evaluation success against env steps (each record's curve), all learners on one task."""
    by: dict[tuple, list] = {}
    for c, r in done:
        if c["kind"] == "agent" and c["target"] == target and r.get("curve"):
            by.setdefault((c["method"], c["variant"]), []).append(np.array(r["curve"], dtype=float))
    styles = _row_styles(list(by))
    fig, ax = plt.subplots(figsize=(10, 5.2), layout="constrained")
    for (method, variant), curves in by.items():
        x = curves[0][:, 0]
        ys = np.stack([np.interp(x, c[:, 0], c[:, 1]) for c in curves])
        _band(ax, x, 100 * ys, f"{method}/{variant} ({len(curves)})", clip=(0.0, 100.0),
              style=styles[(method, variant)])
    ax.set_xscale("log")
    ax.set_xlabel("training env steps")
    ax.set_ylabel("success at 1 cm, evaluation [%]")
    ax.set_ylim(-3, 103)
    ax.grid(alpha=0.3)
    ax.set_title(f"{target}: the learners' success against training env steps" + _second_line(note), fontsize=10)
    fig.legend(fontsize=8, loc="outside right upper", ncol=1 if len(by) <= 22 else 2, frameon=False,
               title="method/variant (seeds):\nmean, 95 % band over seeds", title_fontsize=8)
    return fig


def _planner_error_vs_evals(plt, done: list, target: str, note: str):
    """Planners' mean per-move error against simulator evaluations (x = move k x sim evals per move)."""
    by: dict[tuple, list] = {}
    for c, r in done:
        if c["kind"] == "planner" and c["target"] == target and r.get("sim_evals"):
            by.setdefault((c["method"], c["variant"]), []).append(r)
    styles = _row_styles(list(by))
    fig, ax = plt.subplots(figsize=(10, 4.6), layout="constrained")
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
              label=f"{method}/{variant} ({len(curves)}; {epm:.0f} per move)", style=styles[(method, variant)])
    ax.axhline(1.0, color="k", lw=0.8, ls="--", label="1 cm: success")
    ax.axhline(2.0, color="k", lw=0.8, ls=":", label="2 cm")
    ax.set_xlabel("simulator evaluations (rope-moves simulated)")
    ax.set_ylabel("mean shape error [cm]")
    ax.grid(alpha=0.3)
    ax.set_title(f"{target}: the planners' error against simulator evaluations" + _second_line(note), fontsize=10)
    fig.legend(fontsize=8, loc="outside right upper", frameon=False,
               title="method/variant (seeds;\nsimulator evaluations)", title_fontsize=8)
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
    if target in route_targets(grid):            # a routing task: every row that runs there (none is a main row),
        keep = None                              # a learner on a held-out route by its cells on learner_source
        trained_on = learner_source(grid, target)
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


def final_errors(final: np.ndarray, target: np.ndarray, on_board: bool = False) -> str:
    """A gallery panel's caption: the mean and the worst node's error [mm] of a final shape against its target,
    centroids aligned as the task's errors (diffdlo.tasks.rewards.node_errors), or where they lie (``on_board``: a
    route, whose pegs fix where it lies)."""
    node = (np.linalg.norm(final - target, axis=1) if on_board
            else np.linalg.norm((final - final.mean(0)) - (target - target.mean(0)), axis=1))
    return f"{node.mean() * 1e3:.1f} / {node.max() * 1e3:.1f} mm"


def _gallery(plt, grid: dict[str, Any], done: list, target: str, note: str):
    """Start (grey), final shape (blue) and target (dashed, at the final shape's centroid: the error ignores
    translation) of each seed's first episode, with its final mean and worst node error (``final_errors``), a row
    per method; every panel the same view and scale, and the same
    episode in each column (the episodes are paired) around that column's centre. The view holds 98 % of the drawn
    points, so one rope that drifted off does not shrink every other to a sliver; what lies beyond it is cut at the
    panel's edge."""
    route = target in route_targets(grid)

    def placed(sh):
        """(start, final, target moved onto the final shape's centroid; a route's where it lies) of one episode's
        shapes, and a route's pegs ((K, 3) x, y, radius; empty for a free rope)."""
        final, tgt = np.array(sh["final"]), np.array(sh["target"])
        pegs = np.array(sh.get("pegs") or np.zeros((0, 3)), dtype=float).reshape(-1, 3)
        return (np.array(sh["start"]), final, tgt if route else tgt - tgt.mean(0) + final.mean(0)), pegs

    panels = _gallery_panels(grid, done, target)
    seeds = list(grid["seeds"])
    rows = [(label, [sh if sh is None or isinstance(sh, str) else placed(sh)[0] for sh in row])
            for label, row in panels]
    boards = [[None if sh is None or isinstance(sh, str) else placed(sh)[1] for sh in row] for _, row in panels]
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
    height = 1.9 * len(rows) + 1.0
    fig, axes = plt.subplots(len(rows), len(seeds), figsize=(1.9 * len(seeds) + 2.0, height), squeeze=False,
                             layout="constrained")
    for i, (label, row) in enumerate(rows):
        for j, shapes in enumerate(row):
            ax = axes[i, j]
            ax.set_xlim(centres[j][0] - lim, centres[j][0] + lim)
            ax.set_ylim(centres[j][1] - lim, centres[j][1] + lim)
            ax.set_aspect("equal")
            ax.set_xticks([])
            ax.set_yticks([])
            if i == 0:
                ax.set_title(f"seed {seeds[j]}, episode 0", fontsize=9)
            if not isinstance(shapes, tuple):
                ax.text(*centres[j], "not run" if shapes is None else "ran; shapes\nnot recorded", ha="center",
                        va="center", fontsize=9, color="0.5")
                continue
            start, final, tgt = shapes
            for x, y, r in boards[i][j]:
                ax.add_patch(plt.Circle((x, y), r, color="0.45", zorder=0))
            ax.plot(*start.T, color="0.7", lw=1)
            ax.plot(*tgt.T, "k--", lw=1)
            ax.plot(*final.T, color="tab:blue", lw=1.5)
            ax.text(0.03, 0.03, final_errors(final, tgt, on_board=route), transform=ax.transAxes, fontsize=8,
                    color="0.3", bbox=dict(fc="white", ec="none", alpha=0.8, pad=1))
        axes[i, 0].set_ylabel(label, fontsize=9, rotation=0, ha="right", va="center")
    what = ("route (dashed, on the board), pegs (dark grey discs)" if route
            else "target (dashed; at the final shape's centroid)")
    fig.suptitle(f"{target}: start (grey), final shape (blue), {what}"
                 f"{note}\nin each panel: final error, mean / worst node [mm]; view ±{lim:.2f} m in every panel "
                 "(a column: one episode, one centre)" + ("; shapes beyond it are cut" if cut else ""), fontsize=10)
    return fig


def _pyplot():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(plt, fig, path: Path, dpi: int) -> Path:
    """Write ``fig`` at ``dpi`` (its layout is its own: constrained, the legends outside the axes) and close it."""
    with replacing(path, suffix=path.suffix) as tmp:          # a reader never sees half a picture
        fig.savefig(tmp, dpi=dpi, format=path.suffix.lstrip(".") or None, metadata={"Software": None})
    plt.close(fig)
    return path


# dots per inch of each figure: the line plots come out 800 to 1,000 px wide, the gallery ~900 px
DPI = {"summary": 90, "precision": 90, "success_vs_steps": 90, "planner_error_vs_evals": 85, "gallery": 75,
       "cost": 80}


def figures_to_draw(grid: dict[str, Any], done: list) -> list[tuple[str, Callable, int]]:
    """The figures of ``make_figures`` as (file name, draw: pyplot -> Figure, dpi), none drawn yet: the summary and
    precision figures and, per task, the learners' success curves, the planners' error against simulator
    evaluations and the gallery, from the finished cells ``done`` ([(cell, record)])."""
    tag = "quick_" if grid["name"] == "quick" else ""
    note = " [QUICK RUN: format only]" if tag else ""
    out: list[tuple[str, Callable, int]] = []
    by_key = {_key(c): r for c, r in done}
    if _summary_points(grid, by_key):
        out.append((f"{tag}summary.png", lambda plt: _summary(plt, grid, by_key, note), DPI["summary"]))
    points = ladder_points(grid, by_key)
    if points:
        out.append((f"{tag}precision.png", lambda plt: _precision(plt, points, note), DPI["precision"]))
    done, _ = split_done(grid, done)          # the task figures: the rows read at their own success
    for target in _targets(grid, done):
        if any(c["kind"] == "agent" and c["target"] == target and r.get("curve") for c, r in done):
            out.append((f"{tag}success_vs_steps_{target}.png",
                        lambda plt, t=target: _success_vs_steps(plt, done, t, note), DPI["success_vs_steps"]))
        if any(c["kind"] == "planner" and c["target"] == target and r.get("sim_evals") for c, r in done):
            out.append((f"{tag}planner_error_vs_evals_{target}.png",
                        lambda plt, t=target: _planner_error_vs_evals(plt, done, t, note),
                        DPI["planner_error_vs_evals"]))
        if _gallery_panels(grid, done, target):
            out.append((f"{tag}gallery_{target}.png", lambda plt, t=target: _gallery(plt, grid, done, t, note),
                        DPI["gallery"]))
    return out


def make_figures(grid: dict[str, Any], done: list, figdir: Path) -> list[Path]:
    """Draws ``figures_to_draw`` into ``figdir``. Returns the files written."""
    plt = _pyplot()
    figdir.mkdir(parents=True, exist_ok=True)
    return [_save(plt, draw(plt), figdir / name, dpi) for name, draw, dpi in figures_to_draw(grid, done)]


def _cost(plt, target: str, rows: list[dict[str, Any]], note: str):
    """Cumulative simulator moves and wall seconds against episodes run on one task, planners and learners on the
    same axes, one legend for both panels (a row missing its wall seconds is only in the first)."""
    episodes = np.logspace(0, 4, 60)
    keys = [(r["method"], r["variant"] + ("" if r["trained_on"] == target else f" ({r['trained_on']})"))
            for r in rows]
    styles = _row_styles(keys)
    fig, axes = plt.subplots(1, 2, figsize=(12, 5.2 + 0.2 * math.ceil(len(rows) / 4)), layout="constrained")
    legend: dict[str, Any] = {}
    for ax, key, unit in ((axes[0], "moves", "simulator moves"), (axes[1], "s", "wall seconds")):
        for r, (method, variant) in zip(rows, keys):
            if math.isnan(r[f"episode_{key}"]):
                continue
            label = f"{method}/{variant}: {r['success']:.0%}"
            line, = ax.plot(episodes, r[f"train_{key}"] + episodes * r[f"episode_{key}"], lw=1.4, label=label,
                            **dict(styles[(method, variant)], marker=None))
            legend.setdefault(label, line)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("episodes run")
        ax.set_ylabel(f"cumulative {unit} (training + episodes)")
        ax.grid(alpha=0.3)
    fig.legend(list(legend.values()), list(legend), fontsize=8, loc="outside lower center", frameon=False, ncol=4,
               title="method/variant: success at 1 cm", title_fontsize=8)
    fig.suptitle(f"{target}: the cost of planning against learning" + _second_line(note), fontsize=11)
    return fig


def cost_figures_to_draw(grid: dict[str, Any], costs: dict[str, list[dict[str, Any]]]) \
        -> list[tuple[str, Callable, int]]:
    """The figures of ``make_cost_figures`` as (file name, draw: pyplot -> Figure, dpi), none drawn yet."""
    tag = "quick_" if grid["name"] == "quick" else ""
    note = " [QUICK RUN: format only]" if tag else ""
    return [(f"{tag}cost_{target}.png", lambda plt, t=target, r=rows: _cost(plt, t, r, note), DPI["cost"])
            for target, rows in costs.items()]


def make_cost_figures(grid: dict[str, Any], costs: dict[str, list[dict[str, Any]]], figdir: Path) -> list[Path]:
    """Per task: cumulative simulator moves and wall seconds against episodes solved, planners and learners on the
    same axes (a learner starts at its training cost; where its line crosses CEM's it has paid back)."""
    plt = _pyplot()
    figdir.mkdir(parents=True, exist_ok=True)
    return [_save(plt, draw(plt), figdir / name, dpi) for name, draw, dpi in cost_figures_to_draw(grid, costs)]
