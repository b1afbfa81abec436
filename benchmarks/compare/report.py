"""The markdown report (where --report names; docs/RESULTS.md for the committed one), from the cells' records: the
committed results file (docs/results/cells.jsonl) or the finished cells of a run folder. First the main grid as one
table and one figure, the notes on what wins where, the paired differences against CEM and the cells not run yet with
their cost, the precision rows' section (precision.py, where some of their cells finished: those rows are in no
other table), the routing section (routing.py: the rows among pegs, the pin paired against no pin, their
galleries); then the definitions, one table per task with the exact commands per seed, the galleries, the cost
section and the figures. A finished cell whose settings differ from the grid's now is left out and named at the
top."""
from __future__ import annotations

import json
import math
import os
import shlex
from pathlib import Path
from typing import Any

from .costs import cost_section, row_cost
from .figures import figure_names, make_cost_figures, make_figures
from diffdlo.utils.files import write_text_atomic
from .grid import ROOT, build_cells, cell_dir, main_rows, route_targets
from .precision import precision_section, split_done
from .routing import routing_section
from .records import as_results, make_record, record_changes, record_key
from .settings import changed_cells, describe_changes
from .stats import fmt_ci as _fmt_ci, row_stats
from .summary import cell_minutes, cpu_hours, missing_section, paired_section, readme_table, summary_table

README_BEGIN, README_END = "<!-- summary:begin -->", "<!-- summary:end -->"


def readme_summary(grid: dict[str, Any], records: list[dict[str, Any]], cells: list[dict[str, Any]]) -> str:
    """The README's summary block (between its markers) from the records: the short table and where it comes
    from."""
    loaded, _ = _loaded_from_records(cells, records)
    done = {(c["method"], c["variant"], c["target"], c["seed"]): r for c, r in loaded if r is not None}
    return "\n".join([README_BEGIN, *readme_table(grid, done), "",
                      "Success at 1 cm · mean moves to success, the same episodes for every method "
                      f"({len(grid['seeds'])} seeds × {grid['episodes']} per task; fewer seeds named; empty: not a "
                      "cell of the grid). Written from `docs/results/cells.jsonl` by `python -m benchmarks.compare "
                      "--report-only`.", "",
                      "![Success and moves against the simulator moves each method spent (random targets)]"
                      "(docs/figures/summary.png)", "", summary_caption(grid, "docs/RESULTS.md, its Definitions"),
                      README_END])


def summary_caption(grid: dict[str, Any], names: str) -> str:
    """The text under the summary figure: what its axes count, and where the rows' full names are (``names``)."""
    return (f"The figure: random targets, a marker per main row by its short name (the full names: {names}); "
            "hollow: the row from 64 px pictures. Its x axis: the simulator moves a row "
            f"spent for its {grid.get('episodes', 20)} evaluated episodes, training included (planners: the moves "
            "they simulate and execute; learners: their training env steps and the moves they execute, and "
            "simulate when they act by policy rollouts).")


def update_readme(path: Path | str, block: str) -> bool:
    """Replace the README's summary block with ``block``; False if it has no markers (nothing written)."""
    path = Path(path)
    text = path.read_text() if path.exists() else ""
    if README_BEGIN not in text or README_END not in text:
        return False
    head, rest = text.split(README_BEGIN, 1)
    tail = rest.split(README_END, 1)[1]
    write_text_atomic(path, head + block + tail)
    return True

COLUMNS = ["method", "variant", "seeds × episodes", "success @1 cm: t-CI over seeds; Wilson pooled",
           "success @2 cm (final error < 2 cm): t-CI; Wilson", "final error [cm], t-CI",
           "moves to success (mean; n) (to 2 cm where recorded)", "env steps / cell", "sim evals / episode",
           "wall s / cell (s / move)", "command"]


def _load(cell: dict[str, Any]) -> dict[str, Any] | None:
    """A finished cell's record, read from its folder (results.json and cell.json), in the report's shape."""
    p = cell_dir(cell) / "results.json"
    if not p.exists():
        return None
    cj = cell_dir(cell) / "cell.json"
    meta = json.loads(cj.read_text()) if cj.exists() else {}
    return as_results(make_record(cell, json.loads(p.read_text()), meta))


def task_groups(done: list, target: str) -> dict[tuple[str, str, str], list]:
    """The rows of one task: (method, variant, trained_on) -> [(cell, results)]. On a held-out shape a learner's row
    is its trained policy evaluated there (results "heldout"), one row per task it was trained on."""
    groups: dict[tuple[str, str, str], list] = {}
    for c, r in done:
        if c["target"] == target:
            groups.setdefault((c["method"], c["variant"], target), []).append((c, r))
    for c, r in done:
        held = (r.get("heldout") or {}).get(target)
        if held and c["target"] != target:
            sub = dict(r, episodes=held["episodes"], success_rate=held["success_rate"])
            groups.setdefault((c["method"], c["variant"], c["target"]), []).append((c, sub))
    return groups


def harness_command(grid: str, out: str, method: str, variant: str, target: str, seeds: list[int],
                    learner_device: str | None = None) -> str:
    """The harness command that reruns one row's seeds."""
    q = ["--quick"] if grid == "quick" else []
    dev = ["--learner-device", learner_device] if learner_device else []
    return shlex.join(["python", "-m", "benchmarks.compare", *q, "--methods", method, "--variants", variant,
                       "--targets", target, "--seeds", *map(str, seeds), "--out", out, *dev])


def machine_label(res: dict[str, Any]) -> str:
    """Where a cell ran, as the per-seed list prints it."""
    m = res.get("_machine")
    if not m:
        return "machine not recorded"
    label = f"{m.get('cpus')}-core CPU" + (f" + {m['gpu']}" if m.get("gpu") else "")
    return label + (f"; {m['note']}" if m.get("note") else "")


def _preamble(grid: dict[str, Any], out: Path, loaded: list, doc: Path, source: str) -> list[str]:
    """Title, quick-run warning and where the report comes from."""
    cells = [c for c, _ in loaded]
    n_done = sum(r is not None for _, r in loaded)
    quick = grid["name"] == "quick"
    lines = ["# Results", ""]
    if quick:
        lines += ["> **QUICK RUN — a format example, NOT results.** Generated by "
                  "`python -m benchmarks.compare --quick`",
                  "> (budgets: below). Nothing below measures the methods; the full comparison is "
                  "`python -m benchmarks.compare`.", ""]
    lines += [f"Grid `{grid['name']}` of `benchmarks/compare.yaml`: {n_done} of {len(cells)} cells finished. "
              f"Rebuilt by `{source}`.", ""]
    return lines


def _definitions(grid: dict[str, Any], loaded: list) -> list[str]:
    """Definitions, budgets and the cells not run yet."""
    cells = [c for c, _ in loaded]
    n_done = sum(r is not None for _, r in loaded)
    quick = grid["name"] == "quick"
    lines = ["## Definitions", "",
             "A row aggregates the finished seeds of one method/variant on one task; episode i of a seed's "
             f"{grid['episodes']} evaluation episodes is what one rope's `env.reset(seed={grid['eval_seed_base']} + "
             "1000·seed + i)` draws (its start shape and, on a family of targets, its target), for every method: "
             "the rows of a task are evaluated on the same episodes. "
             "**Success @1 cm**: the episode terminated with shape error < 1 cm (the env's success). "
              "**Success @2 cm**: the episode's last shape error < 2 cm (an episode ends at its first move under 1 cm "
              "or after max-steps moves, for planners and learners alike). "
              "**CIs (95 %)**: first a t-interval over seeds (mean of per-seed rates ± t₀.₉₇₅,ₙ₋₁·sd/√n, clipped "
              "to [0, 1]; `n=1` when only one seed), then a Wilson score interval over the pooled episodes. "
              "**Final error**: per-seed mean of the episodes' last shape error, t-interval over seeds. "
              "**Moves to success**: mean moves of the successful episodes (n = their number); where the "
              "episodes record their per-move errors (every planner; the learners' newer records) also: mean "
              "first move under 2 cm over the episodes that got there. "
              "**Env steps**: learners: training env transitions actually run (the budget, rounded up to a whole "
              "batched step of the run's ropes: PPO cuts its last rollout short); planners: moves executed over the "
              "cell's episodes; APG (a policy trained through the simulator's gradients) adds in brackets the "
              "rope-moves it backpropagated through the simulator in training. "
              "**Sim evals**: rope-moves simulated by a planner per episode (learners: none). "
              "**Wall**: seconds per cell (planners: and planning seconds per move).", ""]
    labelled = [(m, spec["label"]) for m, spec in grid["methods"].items() if spec.get("label")]
    if labelled:
        lines += ["**Methods** (the tables' `method` column): " + "; ".join(f"`{m}`: {label}" for m, label in labelled)
                  + ".", ""]
    if grid.get("budgets"):
        lines += [f"**Budgets.** {' '.join(grid['budgets'].split())}", ""]
    missing: dict[str, list[str]] = {}
    for c, r in loaded:
        if r is None:
            missing.setdefault(f"{c['method']}/{c['variant']}/{c['target']}", []).append(str(c["seed"]))
    if missing and not quick:
        lines += [f"> **Partial comparison: {len(cells) - n_done} of {len(cells)} cells not run yet** "
                  "(method/variant/target: seeds missing): "
                  + "; ".join(f"{k}: {' '.join(v)}" for k, v in missing.items())
                  + ". Rows below aggregate the finished seeds only; absent rows were not run. "
                  + _outside_main_cost(grid, loaded), ""]
    return lines


def _outside_main_cost(grid: dict[str, Any], loaded: list) -> str:
    """What the cells not run outside the main grid (the secondary rows, the precision rows and the named lines) would cost."""
    main = grid.get("main") or {}
    rows = set(main_rows(grid)) | set(main_rows(grid, image=True))
    done = {(c["method"], c["variant"], c["target"], c["seed"]): r for c, r in loaded if r is not None}
    left = [c for c, r in loaded if r is None
            and not ((c["method"], c["variant"]) in rows and c["target"] in main.get("targets", []))]
    if not left:
        return "Every cell outside the main grid has run."
    minutes = [cell_minutes(grid, done, c["method"], c["variant"])[0] for c in left]
    known = [m for m in minutes if not math.isnan(m)]
    return (f"Of them, {len(left)} are outside the main grid (the secondary rows, the precision rows and the named lines): ≈ "
            f"{sum(known) / 60:.1f} CPU-hours at their rows' minutes per cell (measured, else the grid's `cpu_min`)"
            + (f", {len(minutes) - len(known)} cell(s) unpriced" if len(known) < len(minutes) else "") + ".")


def _row(grid: dict[str, Any], out: Path, target: str, key: tuple[str, str, str], items: list):
    """One table row of a task: (its cells' text, row_stats, its costs, its per-seed command lines)."""
    method, variant, trained_on = key
    runs = [r for _, r in items]
    st = row_stats(runs)
    cost = dict(row_cost(method, runs, st), method=method, variant=variant, trained_on=trained_on)
    devices = sorted({r.get("_learner_device") or "" for r in runs})
    row_groups = [(d, [c["seed"] for c, r in items if (r.get("_learner_device") or "") == d]) for d in devices]
    cmd = " ; ".join(harness_command(grid["name"], str(out), method, variant, trained_on, sd, d or None)
                     for d, sd in row_groups)
    if trained_on != target:
        variant = f"{variant}, trained on {trained_on}"
    w = f"{st['wall']:.1f}" + (f" ({st['s_per_move']:.2f})" if st["s_per_move"] is not None else "")
    n_dev = sum(bool(r.get("_learner_device")) for r in runs)
    if n_dev:
        w += f" ({n_dev} of {len(items)} seeds with --learner-device: machines in the per-seed list)"
    moves = "—" if not st["moves"][1] else f"{st['moves'][0]:.1f}; {st['moves'][1]}"
    if not math.isnan(st["moves2"]):
        moves += f" (to 2 cm: {st['moves2']:.1f})"
    text = [method, variant, f"{st['seeds']} × {st['episodes'] // max(st['seeds'], 1)}",
            f"{_fmt_ci(*st['s1'])}; {_fmt_ci(*st['s1_w'])}", f"{_fmt_ci(*st['s2'])}; {_fmt_ci(*st['s2_w'])}",
            _fmt_ci(*st["err"], scale=100.0), moves,
            f"{st['env_steps']:.0f}" + ("" if st.get("sim_backward") is None
                                        else f" ({st['sim_backward']:.0f} sim backward)"),
            "—" if st["sim_evals"] is None else f"{st['sim_evals']:.0f}", w, f"`{cmd}`"]
    details = [f"- {method}/{variant} seed {c['seed']}: `{r['_command']}` ({machine_label(r)})" for c, r in items]
    return text, st, cost, details


KEPT = "<!-- kept by benchmarks.compare --report: the sections below come from other benchmarks -->"


def _loaded_from_folders(cells: list[dict[str, Any]]) -> tuple[list, list]:
    """[(cell, record or None)] of the run folders, and the cells whose stored settings changed (left out)."""
    changed = changed_cells(cells)
    stale = {id(c) for c, _ in changed}
    return [(c, None if id(c) in stale else _load(c)) for c in cells], \
        [describe_changes(c, ch) for c, ch in changed]


def _loaded_from_records(cells: list[dict[str, Any]], records: list[dict[str, Any]]) -> tuple[list, list]:
    """[(cell, record or None)] of the records file, and the records whose settings differ from the grid's now."""
    by = {record_key(r): r for r in records}
    loaded, changed = [], []
    for c in cells:
        rec = by.get((c["method"], c["variant"], c["target"], c["seed"]))
        ch = record_changes(rec, c) if rec is not None else []
        if ch:
            changed.append(f"{c['method']}/{c['variant']}/{c['target']} seed {c['seed']}: " + "; ".join(ch))
        loaded.append((c, None if rec is None or ch else as_results(rec)))
    return loaded, changed


def _notes(grid: dict[str, Any]) -> list[str]:
    """The hand-written reading of the results (the grid's ``notes`` file), if any."""
    path = grid.get("notes")
    if not path or not (ROOT / path).exists():
        return []
    return [(ROOT / path).read_text().rstrip(), ""]


def _bound(grid: dict[str, Any]) -> list[str]:
    """The move bound (benchmarks/move_bound.py's committed results, the grid's ``bound`` file), if any: CEM at
    growing budgets on the same episodes."""
    path = grid.get("bound")
    if not path or not (ROOT / path).exists():
        return []
    res = json.loads((ROOT / path).read_text())
    seeds = " ".join(map(str, res["seeds"]))
    lines = ["## How few moves: CEM at growing budgets", "",
             f"CEM through the simulator on `{res['target']}`, seeds {seeds} × {res['episodes_per_seed']} episodes "
             "(the grid's episodes), at several horizon × candidates × iterations budgets and two costs "
             "(running_weight 0.5: every move's error counts, planners.cem's default; 0: only the state at the "
             "horizon). **vs 2x300x5**: mean difference in moves against the default budget on the episodes both "
             "solved (paired). Planning seconds were measured beside other jobs. Command: "
             f"`{res.get('command', 'python -m benchmarks.move_bound')}`.", "",
             "| budget | running_weight | episodes | success @1 cm | moves | vs 2x300x5 (paired; n) | sim evals / move "
             "| s / move |", "|---|---|---|---|---|---|---|---|"]
    for b in res["summary"]:
        lines.append(f"| {b['budget']} | {b['running_weight']:g} | {b['episodes']} | {100 * b['success']:.0f} % | "
                     f"{b['moves']:.2f} | {b['moves_vs_reference']:+.2f}; {b['paired']} | "
                     f"{b['sim_evals_per_move']:,.0f} | {b['plan_s_per_move']:.2f} |")
    return lines + [""]


def write_report(grid: dict[str, Any], out: Path | str, doc: Path | str, figures: Path | str | None,
                 cells: list[dict[str, Any]] | None = None, records: list[dict[str, Any]] | None = None,
                 source: str | None = None) -> dict[str, Any]:
    """The report ``doc`` (and figures in ``figures``; None: not drawn, still linked) from the finished cells: the
    ``records`` (docs/results/cells.jsonl) if given, else the run folders under ``out``. A finished cell whose
    settings differ from the grid's now counts as not run and is named at the top. ``source``: the command printed
    as the one that rebuilds the report. Returns {target: [row dicts]}."""
    out, doc = Path(out), Path(doc)
    cells = build_cells(grid, out) if cells is None else cells
    if records is None:
        loaded, changed = _loaded_from_folders(cells)
    else:
        loaded, changed = _loaded_from_records(cells, records)
    quick = grid["name"] == "quick"
    source = source or shlex.join(["python", "-m", "benchmarks.compare", *(["--quick"] if quick else []),
                                   "--out", str(out), "--report-only", "--report", str(doc)])
    done = [(c, r) for c, r in loaded if r is not None]
    by_key = {(c["method"], c["variant"], c["target"], c["seed"]): r for c, r in done}
    regular, _ = split_done(grid, done)      # the precision rows have a section of their own, not the task tables
    rel = os.path.relpath(Path(figures) if figures is not None else doc.parent / "figures", doc.parent)
    lines = _preamble(grid, out, loaded, doc, source)
    if changed:
        lines += [f"> **{len(changed)} finished cell(s) ran with other settings than the grid's now: not in the "
                  "tables** (rerun them with `--rerun-changed`): " + "; ".join(changed), ""]
    table: dict[str, list[dict[str, Any]]] = {}
    costs: dict[str, list[dict[str, Any]]] = {}
    sections: list[str] = []
    for target in grid["targets"]:
        groups = task_groups(regular, target)
        if not groups:
            continue
        sections += [f"## Task: {target}", "", "| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
        details = []
        for key, items in groups.items():
            text, st, cost, row_details = _row(grid, out, target, key, items)
            sections.append("| " + " | ".join(text) + " |")
            table.setdefault(target, []).append(dict(zip(COLUMNS, text), stats=st))
            costs.setdefault(target, []).append(cost)
            details += row_details
        sections += ["", "<details><summary>Exact per-seed commands (what the harness ran)</summary>", "", *details,
                     "", "</details>", ""]
    names = figure_names(grid, done, costs)
    if grid.get("main"):
        lines += ["## Summary: success @1 cm · mean moves to success", "",
                  "Each method at its best known settings on the main tasks, then the rows from 64 px pictures. A "
                  "learner's held-out columns are its policy trained on "
                  f"`{(grid.get('main') or {}).get('heldout_trained_on', 'random')}` (the family closest to those "
                  "shapes), evaluated there after training; planners plan for each shape directly. A cell: "
                  "success over all its episodes · mean moves of the successful ones; fewer seeds than the grid's "
                  "are named. Details, intervals and commands: the per-task sections below.", "",
                  *summary_table(grid, by_key), ""]
        summary = [n for n in names if n.endswith("summary.png")]
        lines += [f"![summary]({rel}/{n})" for n in summary] + (["", summary_caption(grid, "the Definitions below"), ""]
                                                                 if summary else [])
        lines += _notes(grid) + paired_section(grid, by_key) + _bound(grid) + missing_section(grid, by_key)
        lines += cpu_hours(grid, by_key)
    precision = [n for n in names if n.endswith("precision.png")]
    lines += precision_section(grid, by_key, f"{rel}/{precision[0]}" if precision else None)
    route_galleries = [n for n in names for t in route_targets(grid) if n.endswith(f"gallery_{t}.png")]
    lines += routing_section(grid, by_key, [f"{rel}/{n}" for n in route_galleries])
    lines += _definitions(grid, loaded) + sections
    if costs:
        lines += cost_section(costs, grid)
    rest = [n for n in names if not n.endswith(("summary.png", "precision.png")) and n not in route_galleries]
    if rest:
        lines += ["## Figures" + (" (quick run: format only, not results)" if quick else ""), ""]
        if any("gallery_" in n for n in rest):
            lines += ["Per task: the learners' success against env steps, the planners' error against simulator "
                      "evaluations, and a gallery: for each row (the main rows where the grid names them) the first "
                      "episode of every seed, a column per seed, so each column is one episode for every row; every "
                      "panel the same scale.", ""]
        lines += [f"![{Path(n).stem}]({rel}/{n})" for n in rest] + [""]
    if figures is not None:
        try:
            written = make_figures(grid, done, Path(figures)) + make_cost_figures(grid, costs, Path(figures))
        except ImportError:
            written = []
        if written and sorted(p.name for p in written) != sorted(names):      # the report would link other files
            raise RuntimeError(f"the figures written {sorted(p.name for p in written)} are not the ones the report "
                               f"links {sorted(names)}")
    kept = ""
    if doc.exists():                           # sections of other benchmarks below the marker survive a rewrite
        old = doc.read_text()
        kept = old[old.index(KEPT):] if KEPT in old else ""
    write_text_atomic(doc, "\n".join(lines) + "\n" + (f"\n{kept}" if kept else ""))
    return table
