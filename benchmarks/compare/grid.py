"""The comparison grid: reading benchmarks/compare.yaml, the cells it spans and their command lines.

A cell is (method, variant, target, seed); it lives in ``<out>/<method>/<variant>/<target>/seed<s>/`` and is
finished when its ``results.json`` exists.
"""
from __future__ import annotations

import math
import shlex
from pathlib import Path
from typing import Any

import yaml

ROOT = Path(__file__).resolve().parents[2]
GRID_FILE = ROOT / "benchmarks" / "compare.yaml"
NAMED = ("horizontal", "vertical", "diagonal", "antidiagonal")


def load_grid(quick: bool = False, path: Path | str = GRID_FILE) -> dict[str, Any]:
    """The ``full`` (or ``quick``) grid of the YAML file, with its name under "name"."""
    grids = yaml.safe_load(Path(path).read_text())
    name = "quick" if quick else "full"
    grid = dict(grids[name], name=name)
    if not isinstance(grid.get("budgets", ""), str):
        raise ValueError(f"{path}: grid {name!r}: 'budgets' must be text (the report prints it), "
                         f"got {grid['budgets']!r}")
    main = grid.get("main") or {}
    for row in [*main.get("rows", []), *main.get("image_rows", [])]:
        method, _, variant = row.partition("/")
        if variant not in grid["methods"].get(method, {}).get("variants", {}):
            raise ValueError(f"{path}: grid {name!r}: main row {row!r} is not a method/variant of the grid")
    bad = [t for t in main.get("targets", []) if t not in grid["targets"]]
    if bad:
        raise ValueError(f"{path}: grid {name!r}: main targets {bad} are not targets of the grid")
    bad = [t for t in grid.get("routes") or {} if t not in grid["targets"]]
    if bad:
        raise ValueError(f"{path}: grid {name!r}: routes {bad} are not targets of the grid")
    for method, spec in grid["methods"].items():
        for variant, v in (spec.get("variants") or {}).items():
            twin = (v or {}).get("paired_with")
            twin_method, _, twin_variant = str(twin).partition("/")
            if twin is not None and twin_variant not in grid["methods"].get(twin_method, {}).get("variants", {}):
                raise ValueError(f"{path}: grid {name!r}: variant {method}/{variant}: paired_with {twin!r} is not "
                                 "a method/variant of the grid")
            if "tolerance" in (v or {}):
                try:
                    check_tolerance(v["tolerance"])
                except ValueError as exc:
                    raise ValueError(f"{path}: grid {name!r}: variant {method}/{variant}: {exc}") from None
    return grid


def _length(value: Any) -> bool:
    """A positive finite number (not a bool, not text)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and value > 0


def check_tolerance(tolerance: Any) -> tuple[float, float | None]:
    """A variant's ``tolerance`` ({mean: M, worst: W}, W optional or null; metres, each a positive finite number)
    as (mean, worst or None); ValueError naming the bad value otherwise."""
    if not isinstance(tolerance, dict):
        raise ValueError(f"'tolerance' must be a mapping {{mean: M, worst: W}} [m] (worst optional), got "
                         f"{tolerance!r}")
    unknown = [k for k in tolerance if k not in ("mean", "worst")]
    if unknown:
        raise ValueError(f"'tolerance' has the keys mean and worst, got {', '.join(map(repr, unknown))} in "
                         f"{tolerance!r}")
    if "mean" not in tolerance:
        raise ValueError(f"'tolerance' needs its mean [m], got {tolerance!r}")
    for key in ("mean", "worst"):
        value = tolerance.get(key)
        if (key == "mean" or value is not None) and not _length(value):
            raise ValueError(f"'tolerance' {key} must be a positive finite number [m]"
                             + (" or null" if key == "worst" else "") + f", got {value!r}")
    worst = tolerance.get("worst")
    return float(tolerance["mean"]), None if worst is None else float(worst)


def row_tolerance(grid: dict[str, Any], method: str, variant: str) -> tuple[float, float | None] | None:
    """The (mean, worst or None) tolerance a row declares (its variant's ``tolerance``: a precision row, read at it
    from its episodes' recorded errors), or None for a row read at its episodes' own success."""
    v = grid["methods"].get(method, {}).get("variants", {}).get(variant) or {}
    return check_tolerance(v["tolerance"]) if "tolerance" in v else None


def route_targets(grid: dict[str, Any]) -> list[str]:
    """The grid's routing tasks (its ``routes``: a task's key -> the env's target, e.g. route_hook_wrap ->
    "route:hook_wrap"), in the grid's order."""
    routes = grid.get("routes") or {}
    return [t for t in grid["targets"] if t in routes]


def learner_source(grid: dict[str, Any], task: str) -> str | None:
    """The task whose cells evaluate a learner on ``task`` after training (their results "heldout"), where a learner
    never trains on ``task`` itself: a held-out shape -> the main ``heldout_trained_on`` (default random), a
    held-out route (the grid's ``heldout_routes``) -> the routing task it maps to; None for every other task."""
    if task in grid.get("heldout", {}):
        return (grid.get("main") or {}).get("heldout_trained_on", "random")
    return (grid.get("heldout_routes") or {}).get(task)


def variant_targets(grid: dict[str, Any], variant: dict[str, Any]) -> list[str]:
    """The tasks a variant runs: its own ``targets``, by default the grid's free-rope tasks (every target but the
    routes: a row runs among pegs only where it says so)."""
    routes = grid.get("routes") or {}
    return list(variant["targets"]) if "targets" in (variant or {}) else [t for t in grid["targets"]
                                                                            if t not in routes]


def env_target(grid: dict[str, Any], target: str) -> str:
    """What a planner is given as --target for the grid's task ``target``: a held-out shape's file, a route's env
    target, else the task's own name."""
    return grid.get("heldout", {}).get(target) or (grid.get("routes") or {}).get(target) or target


def method_label(grid: dict[str, Any], method: str) -> str:
    """The name the report gives a method (its ``label`` in the grid, else its key)."""
    return grid["methods"].get(method, {}).get("label", method)


def row_label(grid: dict[str, Any], method: str, variant: str) -> str:
    """A row's name in a figure: the variant's own ``label`` or ``short`` where it has one (a second row of the same
    method, e.g. "PPO + policy rollouts"), else its method's label."""
    v = grid["methods"].get(method, {}).get("variants", {}).get(variant, {})
    return v.get("label") or v.get("short") or method_label(grid, method)


def main_rows(grid: dict[str, Any], image: bool = False) -> list[tuple[str, str]]:
    """The (method, variant) rows of the main grid (``image``: those from pictures)."""
    return [tuple(r.split("/", 1)) for r in (grid.get("main") or {}).get("image_rows" if image else "rows", [])]


def _flags(args: dict[str, Any]) -> list[str]:
    out: list[str] = []
    for k, v in (args or {}).items():
        out += [f"--{k}", str(v)]
    return out


def _filled(values: dict[str, Any] | None, **fields: Any) -> dict[str, Any]:
    """A variant's args or set with ``{out}``, ``{target}`` and ``{seed}`` in its text values replaced by the cell's
    (a cell that reads another cell's run, e.g. a distillation's teacher: "{out}/ppo/fewest_moves/{target}/seed{seed}")."""
    def fill(v: Any) -> Any:
        if not isinstance(v, str):
            return v
        for k, x in fields.items():
            v = v.replace("{" + k + "}", str(x))
        return v
    return {k: fill(v) for k, v in (values or {}).items()}


def grid_entry(grid: dict[str, Any], spec: dict[str, Any], variant: dict[str, Any]) -> dict[str, Any]:
    """What compare.yaml says of a cell: its variant's entry and the grid-wide settings it uses."""
    return {"kind": spec["kind"], "args": dict(variant.get("args") or {}), "set": dict(variant.get("set") or {}),
            "episodes": grid["episodes"], "eval_seed_base": grid["eval_seed_base"]}


def build_cells(grid: dict[str, Any], out: Path | str, methods=None, variants=None, targets=None,
                seeds=None, learner_device: str | None = None) -> list[dict[str, Any]]:
    """Every (method, variant, target, seed) cell of the grid after the filters, with its commands.

    ``learner_device`` (e.g. "cuda"): learners put their networks and buffers there and simulate on the CPU
    (``--set device=... --set env_device=cpu``); planners are unchanged."""
    out = Path(out)
    cells = []
    for method, spec in grid["methods"].items():
        if methods and method not in methods:
            continue
        for variant, v in spec["variants"].items():
            if variants and variant not in variants:
                continue
            for target in variant_targets(grid, v):
                if target not in grid["targets"] or (targets and target not in targets):
                    continue
                for seed in grid["seeds"]:
                    if seeds is not None and seed not in seeds:
                        continue
                    d = out / method / variant / target / f"seed{seed}"
                    eval_seed = int(grid["eval_seed_base"]) + 1000 * int(seed)
                    cell = {"method": method, "variant": variant, "target": target, "seed": seed,
                            "kind": spec["kind"], "dir": str(d), "grid": grid["name"], "eval_seed": eval_seed,
                            "cwd": str(Path.cwd()),   # relative paths are relative to it (also on Ray workers)
                            "grid_entry": grid_entry(grid, spec, v)}   # stored in cell.json with the argv
                    if spec["kind"] == "agent" and learner_source(grid, target):
                        continue          # learners never train on a held-out shape or route (their rows: results
                                          # "heldout" of the cells on learner_source)
                    filled = {"args": _filled(v.get("args"), out=out, target=target, seed=seed),
                              "set": _filled(v.get("set"), out=out, target=target, seed=seed)}
                    if spec["kind"] == "planner":
                        base = ["-m", f"planners.{method}", *_flags(filled["args"]), "--quiet", "--no-gif"]
                        cell["argv"] = base + ["--target", env_target(grid, target), "--seed", str(eval_seed), "--episodes",
                                               str(grid["episodes"]), "--out", str(d)]
                    else:
                        sets = [x for k, val in filled["set"].items() for x in ("--set", f"{k}={val}")]
                        cell["argv"] = ["-m", spec.get("module", f"agents.{method}"), "--target", env_target(grid, target),
                                        "--seed", str(seed),
                                        *_flags(filled["args"]), "--eval-episodes", str(grid["episodes"]),
                                        "--set", f"eval_seed={eval_seed}", *sets, "--threads", "1", "--no-progress",
                                        "--out", str(d)]
                        if learner_device:
                            cell["argv"][-2:-2] = ["--set", f"device={learner_device}", "--set", "env_device=cpu"]
                            cell["learner_device"] = learner_device
                        cell["total_steps"] = (v.get("args") or {}).get("total-steps")
                    cells.append(cell)
    return cells


def command_line(cell: dict[str, Any]) -> str:
    """The exact command that reproduces a cell, as text."""
    return shlex.join(["python", *cell["argv"]])


def cell_dir(cell: dict[str, Any], sub: str | Path | None = None) -> Path:
    """The cell's folder (or ``sub``, a path relative to the same working directory) from where it runs."""
    return Path(cell.get("cwd", ".")) / (cell["dir"] if sub is None else sub)


def is_done(cell: dict[str, Any]) -> bool:
    return (cell_dir(cell) / "results.json").exists()

