"""The precision rows (compare.yaml's variants with a ``tolerance``, the `precise` ones): each read at its declared
task tolerance, and at a ladder of mean-error tolerances, from its episodes' recorded errors after every move
(``stats.success_move``), not from the episodes' own success (the tolerance the cell ran until).

A planner's precise cell runs until 2 mm (or its max moves): its moves do not depend on the tolerance, so its episode
holds the episode at every looser tolerance exactly. A learner's runs at its row tolerance (trained with it: its
success bonus and episode end are there), so a tighter tolerance is read from moves that stop at the looser success.
Per episode: a tolerance it got within is exact (the move is in the record); one it did not get within is exact too
when the episode ran on to its max moves (or left the workspace), but not when it ended at its own success first: it
might have got there had it gone on. Such an episode counts as a failure, and the row's figure at that tolerance is
a lower bound (marked "≥" in the tables, an open marker in the figure).
"""
from __future__ import annotations

import json
import re
from pathlib import PurePosixPath
from typing import Any

import numpy as np

from .grid import ROOT, method_label, row_tolerance, variant_targets
from .stats import fmt_ci, success_move, t_interval, wilson
from .summary import _episodes, pairs, paired_differences, paired_texts

LADDER = (0.02, 0.01, 0.005, 0.002)      # m: the mean-error tolerances of the success-against-tolerance table
REFERENCE = ("cem", "precise")           # the row the others are paired against
DEFAULT_TOL = 0.01                       # m: the env's success_tol where a cell names none (params/cable.yaml)


def precise_rows(grid: dict[str, Any]) -> list[tuple[str, str, tuple[float, float | None]]]:
    """(method, variant, (mean, worst)) of every row that declares a tolerance, in the grid's order."""
    return [(m, v, tol) for m, spec in grid["methods"].items() for v in spec["variants"]
            if (tol := row_tolerance(grid, m, v)) is not None]


def split_done(grid: dict[str, Any], done: list) -> tuple[list, list]:
    """The finished cells [(cell, record)] as (those read at their own success, the precision rows')."""
    flags = [row_tolerance(grid, c["method"], c["variant"]) is not None for c, _ in done]
    return [x for x, f in zip(done, flags) if not f], [x for x, f in zip(done, flags) if f]


def ran_until(grid: dict[str, Any], method: str, variant: str) -> tuple[float, float | None]:
    """The (mean, worst or None) tolerance a row's cells ran until: a planner's --success-tol and
    --success-worst-tol, a learner's success_tol and success_worst_tol (its variant's args and set), else the env's
    1 cm and none."""
    v = grid["methods"][method]["variants"][variant]
    args, sets = v.get("args") or {}, v.get("set") or {}
    mean = args.get("success-tol", sets.get("success_tol"))
    worst = args.get("success-worst-tol", sets.get("success_worst_tol"))
    return float(DEFAULT_TOL if mean is None else mean), None if worst is None else float(worst)


def length(x: float) -> str:
    """A tolerance as the report names it: "2 cm", "5 mm", "2.5 mm"."""
    cm = round(x * 100, 9)
    return f"{cm:g} cm" if cm >= 1 and cm == int(cm) else f"{round(x * 1000, 9):g} mm"


def tolerance_text(mean: float, worst: float | None) -> str:
    """"5 mm, worst node 2 cm" (or the mean alone)."""
    return length(mean) + ("" if worst is None else f", worst node {length(worst)}")


def episode_at(e: dict[str, Any], tol: float, worst: float | None = None) -> tuple[int | None, bool]:
    """(the move at which an episode is within (``tol``, ``worst``), or None; whether that answer is exact): not
    exact where the episode got no move within it but ended at its own success first (it might have got there had
    it gone on)."""
    if "errors" not in e:
        raise ValueError("a precision row's episode has no recorded errors after each move (a record made before "
                         "they were kept): it cannot be read at another tolerance")
    k = success_move(e["errors"], e.get("worst_errors"), tol, worst)
    return k, k is not None or not e["success"]


def point(runs: list[list[dict]], tol: float, worst: float | None = None) -> dict[str, Any]:
    """A row's success at (``tol``, ``worst``) from its per-seed episode lists: per-seed rates' t-interval, the
    pooled Wilson interval, the mean moves of the episodes within it (and their number), and how many episodes'
    answers are not exact (``censored``: then the rates are lower bounds)."""
    rates, moves, censored = [], [], 0
    for eps in runs:
        found = [episode_at(e, tol, worst) for e in eps]
        rates.append(float(np.mean([k is not None for k, _ in found])))
        moves += [k for k, _ in found if k is not None]
        censored += sum(not exact for _, exact in found)
    n = sum(len(eps) for eps in runs)
    return {"seeds": len(runs), "episodes": n, "rate": t_interval(rates, (0.0, 1.0)), "pooled": wilson(len(moves), n),
            "moves": float(np.mean(moves)) if moves else float("nan"), "solved": len(moves), "censored": censored}


def _runs(episodes: dict[tuple[int, int], dict]) -> list[list[dict]]:
    seeds = sorted({s for s, _ in episodes})
    return [[episodes[k] for k in sorted(episodes) if k[0] == s] for s in seeds]


def precision_data(grid: dict[str, Any], done: dict[tuple, dict]) -> list[dict[str, Any]]:
    """Per precision row and task with finished cells (row, then task, in the grid's order): its episodes, at its
    tolerance and at each ``LADDER`` tolerance of the mean."""
    rows = []
    for method, variant, (tol, worst) in precise_rows(grid):
        v = grid["methods"][method]["variants"][variant]
        for task in [t for t in grid["targets"] if t in variant_targets(grid, v)]:
            eps = _episodes(grid, done, method, variant, task, task)
            if not eps:
                continue
            runs = _runs(eps)
            rows.append({"method": method, "variant": variant, "task": task, "tolerance": (tol, worst),
                         "ran_until": ran_until(grid, method, variant), "episodes": eps,
                         "at_tolerance": point(runs, tol, worst),
                         "ladder": [point(runs, t) for t in LADDER]})
    return rows


def _share(p: dict[str, Any]) -> str:
    """"≥ 85 % · 12.3" (success over all episodes, ≥ where a lower bound; mean moves of the episodes within)."""
    moves = "—" if not p["solved"] else f"{p['moves']:.1f}"
    return ("≥ " if p["censored"] else "") + f"{100 * p['solved'] / p['episodes']:.0f} % · {moves}"


def _bound(p: dict[str, Any], text: str) -> str:
    return f"≥ {text} ({p['censored']} ended at their own success first)" if p["censored"] else text


def _worst_at_success(row: dict[str, Any]) -> str:
    """The worst node's error [mm] at the move each episode got within the row's tolerance: median; 90th percentile
    (n)."""
    tol, worst = row["tolerance"]
    w = []
    for e in row["episodes"].values():
        k, _ = episode_at(e, tol, worst)
        if k is not None and e.get("worst_errors"):
            w.append(1000 * e["worst_errors"][k])
    if not w:
        return "—"
    return f"{np.median(w):.1f}; {np.percentile(w, 90):.1f} (n={len(w)})"


def precision_section(grid: dict[str, Any], done: dict[tuple, dict], figure: str | None = None,
                      reference: tuple[str, str] = REFERENCE) -> list[str]:
    """The report's precision section ([] without a finished precision cell): per precision row and task, success and
    moves at the row's tolerance, paired against ``reference`` on the same episodes, and the worst node's error at
    success; then success against the mean-error tolerance (``LADDER``) and the figure ``figure`` (a path for the
    markdown link)."""
    rows = precision_data(grid, done)
    if not rows:
        return []
    has_reference = reference[1] in grid["methods"].get(reference[0], {}).get("variants", {})
    ref = "/".join(reference)
    ladder = [f"mean < {length(t)}" for t in LADDER]
    tolerances = {r["tolerance"] for r in rows}
    title = tolerance_text(*next(iter(tolerances))) if len(tolerances) == 1 else "each row's tolerance"
    lines = [f"## Precision: success at {title}", "",
             "The precision rows (compare.yaml's `precise` variants, each with a declared `tolerance`), read at that "
             "tolerance from their episodes' recorded mean and worst node errors after each move "
             "(`stats.success_move`), not from the episodes' own success. **ran until**: the tolerance the cells ran "
             "with: a planner's moves do not depend on it (it replans each move, re-seeded per episode), so its "
             "episode run until a tighter one holds the episode at every looser one exactly; a learner is trained "
             "and evaluated at the row's tolerance (its success bonus and episode end are there). **success**: "
             "within the row's tolerance at some move, t-interval over seeds; Wilson pooled. **moves**: mean first move within it, over the episodes "
             "that got there. **Δ vs " + ref + "**: paired on the same episodes (same seed and index, checked as in "
             f"the paired section) against {ref} ({method_label(grid, reference[0])}) at the row's tolerance; Δ "
             "moves over the episodes both got within it. **worst node at success**: the worst node's error at that "
             "move, over the episodes that got there. **≥**: a lower bound: some episodes ended at their own success "
             "(a looser tolerance) before getting within this one, and count as failures.", "",
             "| method | variant | task | tolerance | ran until | seeds × episodes | success: t-CI; Wilson | moves "
             f"(mean; n) | Δ success vs {ref} [pp] | Δ moves vs {ref} (both within) | pairs | worst node at "
             "success [mm]: median; 90th pct |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for row in rows:
        p = row["at_tolerance"]
        tol, worst = row["tolerance"]
        success = _bound(p, f"{fmt_ci(*p['rate'])}; {fmt_ci(*p['pooled'])}")
        moves = "—" if not p["solved"] else f"{p['moves']:.1f}; {p['solved']}"
        paired = ["—", "—", "—"]
        if (row["method"], row["variant"]) == tuple(reference):
            paired = ["(reference)", "(reference)", "—"]
        elif has_reference:
            pr, unverified, mismatched = pairs(row["episodes"],
                                               _episodes(grid, done, *reference, row["task"], row["task"]))
            if pr:
                def outcome(e, tol=tol, worst=worst):
                    k, _ = episode_at(e, tol, worst)
                    return k is not None, k
                ds, dm = paired_differences(pr, outcome)
                paired = paired_texts(ds, dm, len(pr), unverified, mismatched)
        lines.append("| " + " | ".join([
            method_label(grid, row["method"]), row["variant"], row["task"], tolerance_text(tol, worst),
            tolerance_text(*row["ran_until"]), f"{p['seeds']} × {p['episodes'] // max(p['seeds'], 1)}", success,
            moves, *paired, _worst_at_success(row)]) + " |")
    lines += ["", "### Success against the tolerance", "",
              "The same episodes at each tolerance of the mean error alone (no worst-node condition), and at the "
              "row's tolerance: success over all episodes · mean moves of those within it; **≥**: a lower bound (as "
              "above).", "",
              "| method | variant | task | ran until | " + " | ".join(ladder) + " | the row's tolerance |",
              "|" + "---|" * (5 + len(ladder))]
    for row in rows:
        lines.append("| " + " | ".join([
            method_label(grid, row["method"]), row["variant"], row["task"], tolerance_text(*row["ran_until"]),
            *[_share(p) for p in row["ladder"]],
            f"{_share(row['at_tolerance'])} ({tolerance_text(*row['tolerance'])})"]) + " |")
    lines.append("")
    if figure:
        lines += [f"![precision]({figure})", "", figure_caption(grid, done), ""]
    return lines


def _rows_named(points: list[dict[str, Any]]) -> str:
    """"PPO + policy rollouts on random and random_curve; latent world model on random" (the grid's order)."""
    tasks: dict[str, list[str]] = {}
    for p in points:
        tasks.setdefault(p["label"], []).append(p["task"])
    return "; ".join(f"{label} on {' and '.join(t)}" for label, t in tasks.items())


def figure_caption(grid: dict[str, Any], done: dict[tuple, dict]) -> str:
    """What the precision figure draws at each rung: these episodes' exact success, the tolerance ladder's where
    these episodes give only a lower bound and it measured the rung (naming its rows and files), else the bound."""
    points = ladder_points(grid, done)
    measured = [p for p in points if p["ladder"]]
    bounds = [p for p in points if any(not ok and m is None for ok, m in zip(p["exact"], p["measured"]))]
    text = ("In the figure, a filled marker on a solid line is the success of these episodes (exact); markers are "
            "moved a little sideways so that rows at the same success stay visible.")
    if measured:
        files = ", ".join(f"`{f}`" for f in dict.fromkeys(p["ladder"] for p in measured))
        own, rerun = [p for p in measured if not p["rerun"]], [p for p in measured if p["rerun"]]
        text += (" Where these episodes give only a lower bound, a marker with a black edge, reached by a dashed "
                 "line, is the success the tolerance ladder measured (`benchmarks.studies.tolerance_ladder`: the "
                 "cells' final checkpoints re-evaluated on the same start ropes until 2 mm, every rung exact; "
                 f"{files}; docs/PRECISION.md): " + "; ".join(
                     ([f"on these cells: {_rows_named(own)}"] if own else [])
                     + ([f"on the same rows' cells run again with the grid's commands (other run folders than "
                         f"these records'): {_rows_named(rerun)}"] if rerun else [])) + ".")
    if bounds:
        text += (" An open marker with an upward arrow and \"≥\" is a lower bound that nothing measured, with no "
                 f"line into it: {_rows_named(bounds)}.")
    return text


def short_label(grid: dict[str, Any], method: str, variant: str) -> str:
    """A row's name in the figure: its variant's ``short``, else its method's, else the method's key."""
    spec = grid["methods"][method]
    return spec["variants"][variant].get("short") or spec.get("short") or method


def ladder_tables(grid: dict[str, Any]) -> dict[tuple[str, str, str], dict[str, Any]]:
    """The tolerance ladder's measured rungs (the grid's ``ladders``: copies of
    ``benchmarks/studies/tolerance_ladder.py``'s results.json, paths from the repository root), per (method, variant,
    task) of a group named .../<method>/<variant>/<task> (the cells' run folders it re-evaluated): {"file", "group",
    "seeds", "rungs": {tol: success}} with the rungs that are exact there (not lower bounds)."""
    out: dict[tuple[str, str, str], dict[str, Any]] = {}
    for name in grid.get("ladders") or []:
        path = ROOT / name
        for row in json.loads(path.read_text())["rows"]:
            parts = row["group"].rstrip("/").split("/")
            if len(parts) < 3:
                raise ValueError(f"{name}: group {row['group']!r} is not .../<method>/<variant>/<task>")
            rungs = {round(float(r["tol"]), 9): float(r["success"]) for r in row["ladder"] if not r["lower_bound"]}
            out[tuple(parts[-3:])] = {"file": name, "group": row["group"], "seeds": int(row["seeds"]),
                                      "rungs": rungs}
    return out


def _run_folders(done: dict[tuple, dict], method: str, variant: str, task: str) -> set[str]:
    """The folders that hold a row's seeds (the parent of each record's --out), as its command names them."""
    folders = set()
    for key, rec in done.items():
        if key[:3] == (method, variant, task):
            m = re.search(r"--out (\S+)", rec.get("_command") or rec.get("command") or "")
            if m:
                folders.add(PurePosixPath(m.group(1).strip("'\"")).parent.as_posix())
    return folders


def ladder_points(grid: dict[str, Any], done: dict[tuple, dict]) -> list[dict[str, Any]]:
    """The figure's points: per precision row and task, success at each ``LADDER`` tolerance, whether it is exact,
    and ``measured``: where it is not (a lower bound) and the tolerance ladder (``ladder_tables``) measured that rung
    on the row's cells (as many seeds), the ladder's success there, else None; ``ladder``: the ladder's file, or
    None where no rung was taken from it; ``rerun``: whether the ladder re-evaluated other run folders than the
    records' (the same row's cells run again), None where no rung was taken from it."""
    tables = ladder_tables(grid)
    points = []
    for r in precision_data(grid, done):
        table = tables.get((r["method"], r["variant"], r["task"]))
        if table is not None and table["seeds"] != r["at_tolerance"]["seeds"]:
            table = None                                        # not these cells: another set of seeds
        exact = [not p["censored"] for p in r["ladder"]]
        measured = [None if ok or table is None else table["rungs"].get(round(t, 9))
                    for t, ok in zip(LADDER, exact)]
        used = any(m is not None for m in measured)
        points.append({"label": short_label(grid, r["method"], r["variant"]), "method": r["method"],
                       "variant": r["variant"], "task": r["task"], "tols": list(LADDER),
                       "success": [p["solved"] / p["episodes"] for p in r["ladder"]], "exact": exact,
                       "measured": measured, "seeds": r["at_tolerance"]["seeds"],
                       "ladder": table["file"] if used else None,
                       "rerun": (_run_folders(done, r["method"], r["variant"], r["task"]) != {table["group"]})
                       if used else None})
    return points
