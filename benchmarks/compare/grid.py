"""The comparison grid: reading benchmarks/compare.yaml, the cells it spans and their command lines.

A cell is (method, variant, target, seed); it lives in ``<out>/<method>/<variant>/<target>/seed<s>/`` and is
finished when its ``results.json`` exists.
"""
from __future__ import annotations

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
    return grid


def _flags(args: dict[str, Any]) -> list[str]:
    out: list[str] = []
    for k, v in (args or {}).items():
        out += [f"--{k}", str(v)]
    return out


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
            for target in v.get("targets", grid["targets"]):
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
                    if spec["kind"] == "agent" and target in grid.get("heldout", {}):
                        continue          # learners never train on a held-out shape (their rows: results "heldout")
                    if spec["kind"] == "planner":
                        base = ["-m", f"planners.{method}", *_flags(v.get("args")), "--quiet", "--no-gif"]
                        # random: one run per episode on the named target the env draws for it (the runner fills
                        # in "@random"), merged into one results.json. Not one "--target random" run: there the
                        # reset seed's generator draws the target before the start shape (other start shapes than
                        # on a named target) and CEM's generator is seeded once, not per episode
                        if target == "random":
                            cell["subruns"] = [["--target", "@random", "--seed", str(eval_seed + i), "--episodes", "1",
                                                "--out", str(d / f"ep{i}")] for i in range(int(grid["episodes"]))]
                        spec_target = grid.get("heldout", {}).get(target, target)       # a held-out name -> its file
                        cell["argv"] = base + ["--target", spec_target, "--seed", str(eval_seed), "--episodes",
                                               str(grid["episodes"]), "--out", str(d)]
                    else:
                        sets = [x for k, val in (v.get("set") or {}).items() for x in ("--set", f"{k}={val}")]
                        cell["argv"] = ["-m", f"agents.{method}", "--target", target, "--seed", str(seed),
                                        *_flags(v.get("args")), "--eval-episodes", str(grid["episodes"]),
                                        "--set", f"eval_seed={eval_seed}", *sets, "--threads", "1", "--no-progress",
                                        "--out", str(d)]
                        if learner_device:
                            cell["argv"][-2:-2] = ["--set", f"device={learner_device}", "--set", "env_device=cpu"]
                            cell["learner_device"] = learner_device
                        cell["total_steps"] = (v.get("args") or {}).get("total-steps")
                    cells.append(cell)
    return cells


def subrun_argv(cell: dict[str, Any], subrun: list[str], target: str) -> list[str]:
    """The entry point's arguments of one per-episode run of a planner's random cell, on ``target``."""
    head = cell["argv"][:cell["argv"].index("--target")]
    return [*head, "--target", target, *subrun[2:]]


def command_line(cell: dict[str, Any]) -> str:
    """The exact command(s) that reproduce a cell, as text (a random cell's targets are "?" until it has run)."""
    if "subruns" in cell:
        targets = cell.get("subrun_targets", ["?"] * len(cell["subruns"]))
        return " && ".join(shlex.join(["python", *subrun_argv(cell, s, t)]) for s, t in zip(cell["subruns"], targets))
    return shlex.join(["python", *cell["argv"]])


def cell_dir(cell: dict[str, Any], sub: str | Path | None = None) -> Path:
    """The cell's folder (or ``sub``, a path relative to the same working directory) from where it runs."""
    return Path(cell.get("cwd", ".")) / (cell["dir"] if sub is None else sub)


def is_done(cell: dict[str, Any]) -> bool:
    return (cell_dir(cell) / "results.json").exists()

