"""The report's first screen: the main grid as one table (method x task), the paired differences against CEM on the
same episodes, the cells not run yet with their cost, and each method's CPU-hours.

Pairing: episode i of seed s on a task is the same episode for every method (benchmarks/compare.yaml, "Seeds");
each record keeps the episode's start error and target, and two methods' episodes are counted as paired only where
those agree (to 1e-6 m), so a change of the rule would show here as unpaired episodes, not as a silent difference.
"""
from __future__ import annotations

import math
from typing import Any, Callable

import numpy as np

from .costs import acting_sim_evals
from .grid import learner_source, main_rows, method_label, variant_targets
from .stats import t_interval

PAIR_TOL = 1e-6          # m: two episodes with start errors this close (and the same target) are the same episode


def heldout_source(grid: dict[str, Any]) -> str:
    """The task a learner's held-out columns come from (the grid's main ``heldout_trained_on``; default random)."""
    return (grid.get("main") or {}).get("heldout_trained_on", "random")


def task_source(grid: dict[str, Any], method: str, variant: str, task: str) -> str | None:
    """The task whose cells hold a row's episodes on ``task``, or None where the row does not run there: a learner
    on a held-out shape (route) is evaluated there by its cells trained on ``learner_source`` (if its variant
    evaluates the held-out targets, ``eval_targets``); every other row by its own cells on the task."""
    spec = grid["methods"][method]
    v = spec["variants"][variant]
    targets = variant_targets(grid, v)
    source = learner_source(grid, task) if spec["kind"] == "agent" else None
    if source is not None:
        return source if source in targets and "eval_targets" in (v.get("set") or {}) else None
    return task if task in targets else None


def _episodes(grid: dict[str, Any], done: dict[tuple, dict], method: str, variant: str, task: str,
              trained_on: str) -> dict[tuple[int, int], dict]:
    """(seed, episode) -> episode record of one row on one task (a learner on a held-out shape or route: its
    evaluation there after training on ``trained_on``)."""
    out = {}
    for seed in grid["seeds"]:
        held = learner_source(grid, task) is not None and grid["methods"][method]["kind"] == "agent"
        res = done.get((method, variant, trained_on if held else task, seed))
        if res is None:
            continue
        eps = (res.get("heldout") or {}).get(task, {}).get("episodes") if held else res["episodes"]
        for i, e in enumerate(eps or []):
            out[(seed, i)] = e
    return out


def _row_runs(grid, done, method, variant, task, trained_on) -> tuple[list[dict], int]:
    """The per-seed episode lists of a row on a task and the number of seeds they came from."""
    eps = _episodes(grid, done, method, variant, task, trained_on)
    seeds = sorted({s for s, _ in eps})
    return [[eps[k] for k in sorted(eps) if k[0] == s] for s in seeds], len(seeds)


def _cell_text(runs: list[list[dict]], n_seeds: int, n_all: int, variant: dict | None = None) -> str:
    """"100 % · 9.2" (success @1 cm over all episodes; mean moves of the successful ones), seeds if not all.
    None run: "not run", or "too costly here" for a ``variant`` the grid marks so (`too_costly_here`)."""
    if not runs:
        return "not run: too costly here" if (variant or {}).get("too_costly_here") else "not run"
    eps = [e for r in runs for e in r]
    succ = [e["steps"] for e in eps if e["success"]]
    moves = f"{np.mean(succ):.1f}" if succ else "—"
    text = f"{100 * len(succ) / len(eps):.0f} % · {moves}"
    return text + (f" ({n_seeds}/{n_all} seeds)" if n_seeds < n_all else "")


def _costs(grid, done, method, variant, targets) -> tuple[str, str, str]:
    """(training env steps, simulator moves per episode, wall) of a row, from its cells on ``targets``."""
    cells = [done[k] for k in done if k[:2] == (method, variant) and k[2] in targets]
    if not cells:
        return "—", "—", "—"
    eps = [e for r in cells for e in r["episodes"]]
    moves = float(np.mean([e["steps"] for e in eps]))
    if grid["methods"][method]["kind"] == "planner":
        per_ep = float(np.mean([r.get("sim_evals", 0) / len(r["episodes"]) for r in cells])) + moves
        wall = float(np.mean([r["wall_s"] / len(r["episodes"]) for r in cells]))
        return "—", f"{per_ep:,.0f}", f"{wall:.1f} s / episode"
    steps = float(np.mean([r["env_steps"] for r in cells]))
    back = [r["sim_backward"] for r in cells if r.get("sim_backward") is not None]
    teacher = [r["teacher_sim_evals"] for r in cells if r.get("teacher_sim_evals") is not None]
    train = (f"{steps:,.0f}" + (f" (+{np.mean(back):,.0f} backward)" if back else "")
             + (f" (+{np.mean(teacher):,.0f} teacher rollouts)" if teacher else ""))
    wall = float(np.mean([r["wall_s"] for r in cells]))
    acting = acting_sim_evals(cells)
    per_episode = f"{moves * (1 + acting):,.0f}" if acting else f"{moves:.1f}"
    return train, per_episode, f"{wall / 60:.0f} min to train"


def summary_table(grid: dict[str, Any], done: dict[tuple, dict]) -> list[str]:
    """The main grid as markdown: one row per main method (then the rows from pictures), one column per main task."""
    main = grid.get("main") or {}
    tasks = main.get("targets", [])
    n_all = len(grid["seeds"])
    head = ["method", "variant", *tasks, "training env steps", "sim moves / episode", "wall"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for image in (False, True):
        rows = main_rows(grid, image)
        if image and rows:
            lines.append("| **from 64 px pictures** |" + " |" * (len(head) - 1))
        for method, variant in rows:
            texts = []
            for task in tasks:
                source = task_source(grid, method, variant, task)
                if source is None:
                    texts.append("")
                    continue
                runs, n = _row_runs(grid, done, method, variant, task, source)
                texts.append(_cell_text(runs, n, n_all, grid["methods"][method]["variants"][variant]))
            train, per_ep, wall = _costs(grid, done, method, variant, ["random"])
            lines.append("| " + " | ".join([method_label(grid, method), variant, *texts, train, per_ep, wall])
                         + " |")
    return lines


def readme_table(grid: dict[str, Any], done: dict[tuple, dict]) -> list[str]:
    """The README's short form of the summary, one line per main row (named by the variant's ``short``, else the
    method's): random, random_curve, the held-out shapes pooled (``task_source``) and random from 64 px pictures (the
    method's image row), with its training env steps and the simulator moves of one episode (on random, from node
    positions)."""
    heldout = [t for t in (grid.get("main") or {}).get("targets", []) if t in grid.get("heldout", {})]
    n_all = len(grid["seeds"])
    images = dict(main_rows(grid, image=True))
    head = ["method", "random", "random_curve", f"held-out shapes ({len(heldout)})", "random, from 64 px pictures",
            "training env steps", "sim moves / episode"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    pictured: set[str] = set()
    for method, variant in main_rows(grid):
        spec = grid["methods"][method]
        v = spec["variants"][variant]
        texts = []
        for task in ("random", "random_curve"):
            runs, n = _row_runs(grid, done, method, variant, task, task)
            texts.append(_cell_text(runs, n, n_all) if task_source(grid, method, variant, task) else "")
        held_runs, seeds, runs_there = [], set(), False
        for task in heldout:
            source = task_source(grid, method, variant, task)
            if source is None:
                continue
            runs_there = True
            runs, _ = _row_runs(grid, done, method, variant, task, source)
            held_runs += runs
            seeds |= {s for s in grid["seeds"] if (method, variant, source, s) in done}
        texts.append(_cell_text(held_runs, len(seeds), n_all) if held_runs else ("not run" if runs_there else ""))
        if method in images and method not in pictured:       # a method's image row, beside its first main row
            pictured.add(method)
            runs, n = _row_runs(grid, done, method, images[method], "random", "random")
            texts.append(_cell_text(runs, n, n_all, spec["variants"][images[method]]))
        else:
            texts.append("")
        train, per_ep, _ = _costs(grid, done, method, variant, ["random"])
        lines.append("| " + " | ".join([v.get("short", spec.get("short", method)), *texts, train, per_ep]) + " |")
    return lines


def pairs(a: dict[tuple, dict], b: dict[tuple, dict]) -> tuple[list[tuple[dict, dict]], int, int]:
    """The episodes two rows share: ([(episode of a, episode of b)], unverifiable, mismatched). An episode pair whose
    start errors or targets differ is mismatched and left out; one without a start error to compare is kept and
    counted as unverifiable."""
    out, unverified, mismatched = [], 0, 0
    for k in sorted(set(a) & set(b)):
        ea, eb = a[k], b[k]
        if "start_error" not in ea or "start_error" not in eb:
            unverified += 1
        elif abs(ea["start_error"] - eb["start_error"]) > PAIR_TOL or \
                ea.get("target_name") != eb.get("target_name"):
            mismatched += 1
            continue
        out.append((ea, eb))
    return out, unverified, mismatched


def _ci(values: list[float], scale: float = 1.0, nd: int = 1, bounds: tuple[float, float] | None = None) -> str:
    """Mean [95 % t-interval], the interval clipped to ``bounds`` (the values' possible range) when given."""
    if not values:
        return "—"
    m, lo, hi = t_interval(values)
    if bounds is not None and not math.isnan(lo):
        lo, hi = max(lo, bounds[0]), min(hi, bounds[1])
    if math.isnan(lo):
        return f"{m * scale:+.{nd}f} (no interval)"         # one value; its count is in another column
    return f"{m * scale:+.{nd}f} [{lo * scale:+.{nd}f}, {hi * scale:+.{nd}f}]"


def paired_section(grid: dict[str, Any], done: dict[tuple, dict], reference: tuple[str, str] = ("cem", "default")
                   ) -> list[str]:
    """Each main row against CEM on the same episodes, per main task: the difference in success and, on the episodes
    both solved, in moves, with 95 % paired t-intervals over the episode pairs."""
    main = grid.get("main") or {}
    if reference not in main_rows(grid):
        return []
    lines = ["## Paired against CEM, episode by episode", "",
             f"Each row minus {method_label(grid, reference[0])} on the same episodes (same seed, same episode index: "
             "the same start shape and target, checked from each episode's start error and target). **Δ success**: "
             "percentage points, over all paired episodes; **Δ moves**: over the episodes both solved (negative: "
             "fewer moves than CEM). Brackets: 95 % paired t-interval over episode pairs (Δ success clipped to "
             "±100), none for one pair. **pairs**: paired episodes (unverifiable: recorded before episodes kept their "
             "start error; mismatched ones are left out).", "",
             "| method | variant | task | Δ success [pp] | Δ moves (both solved) | pairs |",
             "|---|---|---|---|---|---|"]
    for image in (False, True):
        for method, variant in main_rows(grid, image):
            if (method, variant) == reference:
                continue
            for task in main.get("targets", []):
                source = task_source(grid, method, variant, task)
                if source is None:
                    continue
                a = _episodes(grid, done, method, variant, task, source)
                b = _episodes(grid, done, *reference, task, task)
                if not a or not b:
                    continue
                pr, unverified, mismatched = pairs(a, b)
                if not pr:
                    continue
                ds, dm = paired_differences(pr)
                lines.append("| " + " | ".join([method_label(grid, method), variant, task,
                                                *paired_texts(ds, dm, len(pr), unverified, mismatched)]) + " |")
    return lines + [""]


def own_outcome(e: dict[str, Any]) -> tuple[bool, int | None]:
    """An episode's (success, moves) as it ran: its own success and its moves."""
    return bool(e["success"]), e["steps"]


def paired_differences(pr: list[tuple[dict, dict]], outcome: Callable[[dict], tuple[bool, int | None]] = own_outcome
                       ) -> tuple[list[float], list[float]]:
    """(Δ success per pair, Δ moves per pair both solved) of paired episodes (``pairs``), each episode's (success,
    moves) read by ``outcome`` (default: as it ran; the precision section: at a row's tolerance)."""
    ds, dm = [], []
    for x, y in pr:
        (sx, mx), (sy, my) = outcome(x), outcome(y)
        ds.append(float(sx) - float(sy))
        if sx and sy:
            dm.append(float(mx - my))
    return ds, dm


def paired_texts(ds: list[float], dm: list[float], n: int, unverified: int, mismatched: int) -> list[str]:
    """The cells "Δ success [pp]", "Δ moves (both solved)", "pairs" of a paired row."""
    note = f"{n}" + (f" ({unverified} unverifiable)" if unverified else "") + \
        (f" ({mismatched} mismatched, left out)" if mismatched else "")
    return [_ci(ds, 100, 0, bounds=(-1.0, 1.0)), _ci(dm) + f" (n={len(dm)})", note]


def cell_minutes(grid: dict[str, Any], done: dict[tuple, dict], method: str, variant: str) -> tuple[float, bool]:
    """(minutes, measured) one cell of a row costs: the mean wall of the row's finished cells, or, for a row with
    none, compare.yaml's ``cpu_min`` (an estimate; nan when it has none)."""
    walls = [float(r["wall_s"]) for (m, v, _, _), r in done.items() if (m, v) == (method, variant) and "wall_s" in r]
    if walls:
        return float(np.mean(walls)) / 60, True
    return float(grid["methods"][method]["variants"][variant].get("cpu_min", float("nan"))), False


def missing_section(grid: dict[str, Any], done: dict[tuple, dict]) -> list[str]:
    """The main grid's cells not run yet, one line per row with its cost (minutes per cell x cells)."""
    main = grid.get("main") or {}
    rows = []
    total = 0.0
    for image in (False, True):
        for method, variant in main_rows(grid, image):
            v = grid["methods"][method]["variants"][variant]
            parts, n = [], 0
            for target in variant_targets(grid, v):
                if target not in main.get("targets", []) or (grid["methods"][method]["kind"] == "agent"
                                                            and target in grid.get("heldout", {})):
                    continue
                seeds = [s for s in grid["seeds"] if (method, variant, target, s) not in done]
                if seeds:
                    parts.append(f"{target} ({' '.join(map(str, seeds))})")
                    n += len(seeds)
            if parts:
                minutes, measured = cell_minutes(grid, done, method, variant)
                cost = n * minutes / 60
                total += 0.0 if math.isnan(cost) else cost
                per_cell = ("unknown" if math.isnan(minutes)
                            else f"{minutes:.0f} ({'measured' if measured else 'estimate'})")
                why = v.get("too_costly_here") or "queued: `benchmarks/main_grid.sh` runs it"
                rows.append(f"| {method}/{variant} | {n} | {'; '.join(parts)} | {per_cell} | "
                            + ("unknown" if math.isnan(cost) else f"{cost:.1f}") + f" | {why} |")
    if not rows:
        return ["**The main grid is complete**: every main row on every main task, "
                f"{len(grid['seeds'])} seeds × {grid['episodes']} episodes.", ""]
    return ["## Main-grid cells not run yet", "",
            f"≈ {total:.1f} CPU-hours in all, each cell priced at the mean wall of its row's finished cells (one "
            "process per core on the 2-core machine), or for a row with none at the grid's `cpu_min` estimate. A "
            "learner's held-out columns come with its `random` cells. A cell runs with `python -m benchmarks.compare "
            "--methods M --variants V --targets T --seeds S`.", "",
            "| row | cells | task (seeds) | CPU-minutes per cell | CPU-hours | why not run |",
            "|---|---|---|---|---|---|", *rows, ""]


def cpu_hours(grid: dict[str, Any], done: dict[tuple, dict]) -> list[str]:
    """Each method's CPU-hours over its finished cells (each cell one process on one core: its wall time)."""
    by: dict[str, list[float]] = {}
    for (method, *_), r in done.items():
        by.setdefault(method, []).append(float(r.get("wall_s", 0.0)))
    if not by:
        return []
    parts = [f"{method_label(grid, m)} {sum(w) / 3600:.1f} ({len(w)} cell{'s' if len(w) != 1 else ''})" for m, w in
             sorted(by.items(), key=lambda kv: list(grid["methods"]).index(kv[0]) if kv[0] in grid["methods"] else 99)]
    total = sum(sum(w) for w in by.values()) / 3600
    return [f"**CPU-hours of the finished cells** (each cell one process on one core, so its wall time; {total:.1f} "
            "in all): " + "; ".join(parts) + ".", ""]
