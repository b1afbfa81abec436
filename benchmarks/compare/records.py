"""The comparison's results as data that travels with the code: one compact record per finished cell in a JSON-lines
file (the committed one: docs/results/cells.jsonl), from which the report and its figures are rebuilt without the
run folders.

A record holds the cell (method, variant, target, seed), the command that ran it and its settings (the argv without
--out, as settings.comparable_argv), where it ran, its costs (env steps, simulator evaluations, wall seconds), each
evaluated episode (success, moves, final and start error, target; the mean and the worst node's error after the
reset and after each move, "errors" and "worst_errors", where the cell recorded them: a planner's "errors" always,
the rest since they are recorded; a record without them reads as before), the held-out evaluations of a learner,
the first episode's shapes (the galleries) and a learner's evaluation curve.

    python -m benchmarks.compare --collect --out runs/compare     # add the finished cells of runs/compare
    python -m benchmarks.compare --report-only                    # rebuild docs/RESULTS.md from the records
"""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

from diffdlo.utils.files import write_text_atomic
from .grid import ROOT, cell_dir, command_line
from .settings import argv_changes, comparable_argv

RESULTS_FILE = ROOT / "docs" / "results" / "cells.jsonl"
EPISODE_KEYS = ("success", "steps", "final_error", "start_error", "target_name",
                "sides_kept",     # a route's side test at the episode's end (routing cells only)
                "escape_moves",   # the greedy moves of a planner's stall escape (--escape rows only)
                "seen_error_mm")  # a planner's reading from pictures: mean node error over the moves (--perception)
KEY = ("method", "variant", "target", "seed")


def _episode(e: dict[str, Any]) -> dict[str, Any]:
    out = {k: e[k] for k in EPISODE_KEYS if k in e}
    for k in ("final_error", "start_error"):
        if k in out:
            out[k] = round(float(out[k]), 7)           # 0.1 µm: the pairing check compares to 1e-6 m
    for k in ("errors", "worst_errors"):               # the errors after each move (figures, moves to 2 cm,
        if k in e:                                     # success at another tolerance: stats.success_move)
            out[k] = [floor_error(x) for x in e[k]]
    return out


def floor_error(x: float) -> float:
    """An error [m] as a record keeps it after each move: rounded DOWN to 10 µm (5 decimals), so that x < tol reads
    the same before and after for every tolerance that is a multiple of 10 µm (2 cm, 1 cm, 5 mm, 2 mm): an episode
    that ends just under its tolerance is still under it in its record. (Records collected before worst_errors were
    kept rounded to the nearest 10 µm, which puts about 1 in 500 such last moves on the tolerance itself.)"""
    x = float(x)
    k = math.floor(x * 1e5)
    while (k + 1) / 1e5 <= x:        # the largest k / 1e5 <= x, whatever the product's rounding
        k += 1
    while k / 1e5 > x:
        k -= 1
    return k / 1e5


def _curve(d: Path) -> list[list[float]]:
    """A learner's evaluations during training: [[env step, success rate, mean episode length], ...]."""
    p = d / "eval.csv"
    if not p.exists():
        return []
    from agents.common.logs import read_csv

    rows = [r for r in read_csv(p) if r.get("success_rate") not in (None, "")]
    return [[int(float(r["step"])), round(float(r["success_rate"]), 4),
             round(float(r.get("mean_length") or "nan"), 2)] for r in rows]


def make_record(cell: dict[str, Any], res: dict[str, Any], meta: dict[str, Any]) -> dict[str, Any]:
    """The record of a finished cell from its results.json (``res``) and cell.json (``meta``)."""
    rec: dict[str, Any] = {k: cell[k] for k in KEY}
    rec["kind"] = cell["kind"]
    command = meta.get("command") or command_line(cell)
    if meta.get("resume_command"):               # a cell continued elsewhere from its checkpoint
        command += "` then `" + meta["resume_command"]
    rec["command"] = command
    rec["argv"] = comparable_argv(meta.get("argv", cell["argv"]), meta.get("learner_device"))
    rec["machine"] = meta.get("machine")
    rec["learner_device"] = meta.get("learner_device")
    for k in ("env_steps", "wall_s", "sim_evals", "plan_s_per_step", "eval_s_per_episode", "sim_backward",
              "sim_evals_per_move",           # a learner acting by rollouts (agents/common/rollout.py)
              "teacher_sim_evals"):           # a distilled policy's teacher's rollouts in training (agents/distill.py)
        if res.get(k) is not None:
            rec[k] = res[k]
    rec["episodes"] = [_episode(e) for e in res["episodes"]]
    if res.get("shapes"):
        rec["shapes"] = res["shapes"]
    if res.get("heldout"):
        rec["heldout"] = {label: {"target": h.get("target"), "episodes": [_episode(e) for e in h["episodes"]],
                                  **({"shapes": h["shapes"]} if h.get("shapes") else {})}
                          for label, h in res["heldout"].items()}
    if cell["kind"] == "agent":
        rec["curve"] = _curve(cell_dir(cell))
    return rec


def record_key(rec: dict[str, Any]) -> tuple:
    return tuple(rec[k] for k in KEY)


def read_records(path: Path | str = RESULTS_FILE) -> list[dict[str, Any]]:
    """The records of a JSON-lines file ([] if it does not exist). A line that is not a record is an error naming
    the file and the line."""
    path = Path(path)
    if not path.exists():
        return []
    records = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        try:
            rec = json.loads(line)
            record_key(rec), rec["episodes"]
        except (ValueError, KeyError, TypeError) as exc:
            raise ValueError(f"{path}:{n}: not a cell record ({type(exc).__name__}: {exc})") from None
        records.append(rec)
    return records


def write_records(records: list[dict[str, Any]], path: Path | str = RESULTS_FILE) -> None:
    """Write ``records`` sorted by cell, one JSON object per line (compact, stable: a rerun of the same cells writes
    the same file)."""
    ordered = sorted(records, key=lambda r: (r["method"], r["variant"], r["target"], int(r["seed"])))
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(path, "".join(json.dumps(r, separators=(",", ":"), sort_keys=True) + "\n" for r in ordered))


def collect(loaded: list[tuple[dict[str, Any], dict[str, Any] | None, dict[str, Any] | None]],
            path: Path | str = RESULTS_FILE) -> tuple[int, int]:
    """Add the finished cells of ``loaded`` ([(cell, results or None, cell.json or None)]) to the records in
    ``path``, replacing the records of the same cells. Returns (added or replaced, total)."""
    records = {record_key(r): r for r in read_records(path)}
    n = 0
    for cell, res, meta in loaded:
        if res is not None:
            rec = make_record(cell, res, meta or {})
            records[record_key(rec)] = rec
            n += 1
    write_records(list(records.values()), path)
    return n, len(records)


def record_changes(rec: dict[str, Any], cell: dict[str, Any]) -> list[str]:
    """How the settings a record ran with differ from the grid's cell now ([] if they match)."""
    return argv_changes(rec["argv"], comparable_argv(cell["argv"], cell.get("learner_device")))


def as_results(rec: dict[str, Any]) -> dict[str, Any]:
    """A record in the shape the report reads (the fields of results.json plus "_command", "_machine",
    "_learner_device")."""
    res = {k: v for k, v in rec.items() if k not in ("command", "machine", "learner_device", "argv")}
    res["_command"], res["_machine"], res["_learner_device"] = rec["command"], rec.get("machine"), \
        rec.get("learner_device")
    res["success_rate"] = _rate(rec["episodes"])
    if rec.get("heldout"):
        res["heldout"] = {label: dict(h, success_rate=_rate(h["episodes"])) for label, h in rec["heldout"].items()}
    return res


def _rate(episodes: list[dict[str, Any]]) -> float:
    return sum(e["success"] for e in episodes) / max(len(episodes), 1)
