"""The settings a finished cell ran with, against the grid's now: a cell whose compare.yaml entry changed after it
finished is never reported as if it had run with the new one.

cell.json stores the cell's argv (and a random planner cell's per-episode runs) and its grid entry. What is compared
is the argv without what does not change the result: the --out folder and the --learner-device flags (a learner
may move between a GPU and the CPU). Cells written before the grid entry was stored compare by their argv alone."""
from __future__ import annotations

import json
import shutil
import time
from pathlib import Path
from typing import Any

from .grid import cell_dir, is_done


def comparable_argv(argv: list[str], learner_device: str | None = None) -> list[str]:
    """``argv`` without "--out X" and the "--set device=D --set env_device=cpu" that --learner-device D adds."""
    out, skip = [], 0
    device_sets = {f"device={learner_device}", "env_device=cpu"} if learner_device else set()
    for i, a in enumerate(argv):
        if skip:
            skip -= 1
            continue
        if a == "--out":
            skip = 1
            continue
        if a == "--set" and i + 1 < len(argv) and argv[i + 1] in device_sets:
            device_sets.discard(argv[i + 1])
            skip = 1
            continue
        out.append(a)
    return out


def _is_flag(token: str) -> bool:
    if not token.startswith("-"):
        return False
    try:
        float(token)
        return False
    except ValueError:
        return True


def _flag_values(argv: list[str]) -> dict[str, str]:
    """{"--flag": value} ("--set KEY" per config key; a flag without a value: "")."""
    found: dict[str, str] = {}
    i = 0
    while i < len(argv):
        flag, value = argv[i], ""
        if i + 1 < len(argv) and not _is_flag(argv[i + 1]):
            value, i = argv[i + 1], i + 1
        if flag == "--set" and "=" in value:
            key, value = value.split("=", 1)
            flag = f"--set {key}"
        found[flag] = value
        i += 1
    return found


def argv_changes(stored: list[str], now: list[str]) -> list[str]:
    """What differs between two argvs, flag by flag: "--candidates 300 -> 200", "--set lr added (0.1)"."""
    a, b = _flag_values(stored), _flag_values(now)
    changes = []
    for flag in [*a, *(f for f in b if f not in a)]:
        if flag not in b:
            changes.append(f"{flag} removed (was {a[flag]!r})" if a[flag] else f"{flag} removed")
        elif flag not in a:
            changes.append(f"{flag} added ({b[flag]!r})" if b[flag] else f"{flag} added")
        elif a[flag] != b[flag]:
            changes.append(f"{flag} {a[flag]!r} -> {b[flag]!r}")
    if not changes and stored != now:
        changes.append(f"command line {stored} -> {now}")
    return changes


def stored_cell(cell: dict[str, Any]) -> dict[str, Any] | None:
    p = cell_dir(cell) / "cell.json"
    try:
        return json.loads(p.read_text())
    except (FileNotFoundError, ValueError):
        return None


def has_progress(cell: dict[str, Any]) -> bool:
    """Finished, or holding work a rerun would keep: a learner's checkpoint (resumed)."""
    return is_done(cell) or (cell_dir(cell) / "checkpoint.pt").exists()


def settings_changes(cell: dict[str, Any]) -> list[str]:
    """How the stored settings of ``cell`` (finished, or with work a rerun would keep) differ from the grid's now
    ([] if they match, there is no such work, or no cell.json to compare with)."""
    if not has_progress(cell):
        return []
    meta = stored_cell(cell)
    if meta is None or "argv" not in meta:
        return []
    changes = argv_changes(comparable_argv(meta["argv"], meta.get("learner_device")),
                           comparable_argv(cell["argv"], cell.get("learner_device")))
    return changes


def changed_cells(cells: list[dict[str, Any]]) -> list[tuple[dict[str, Any], list[str]]]:
    """The cells whose finished (or kept) work ran with other settings than the grid's, each with what changed."""
    found = [(c, settings_changes(c)) for c in cells]
    return [(c, ch) for c, ch in found if ch]


def cell_label(cell: dict[str, Any]) -> str:
    return f"{cell['method']}/{cell['variant']}/{cell['target']} seed {cell['seed']}"


def describe_changes(cell: dict[str, Any], changes: list[str]) -> str:
    return f"{cell_label(cell)} ({cell_dir(cell)}): " + "; ".join(changes)


def supersede(cell: dict[str, Any], out: Path | str) -> Path:
    """Move a changed cell's folder to ``<out>/superseded/<time>/<method>/<variant>/<target>/seed<s>`` (kept, not
    reported) so that the cell reruns into a fresh folder. Returns where it went."""
    src = cell_dir(cell)
    dest = (cell_dir(cell, out) / "superseded" / time.strftime("%Y%m%d-%H%M%S") / cell["method"] / cell["variant"]
            / cell["target"] / src.name)
    dest.parent.mkdir(parents=True, exist_ok=True)
    shutil.move(str(src), str(dest))
    return dest
