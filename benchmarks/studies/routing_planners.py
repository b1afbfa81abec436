"""The planners on routes among pegs (docs/ROUTING.md): greedy, CEM and the gradient planner on random routes and
the held-out layouts, with and without the pin, on the same episodes (seed 0 + i: the same board and start for
every planner), and the pin's effect paired episode by episode.

    python -m benchmarks.studies.routing_planners --out runs/routing                 # runs what is missing, prints
    python -m benchmarks.studies.routing_planners --out runs/routing --record docs/results/routing_planners.json

Each cell is one planner command (``python -m planners.<planner> --target T --pin P --episodes E --seed 0
--max-steps 40``, its progress bars shown) into OUT/<planner>-<target>-pin<P>; a cell whose results.json exists is
read, not re-run, so a stopped study continues where it stopped (``--rerun`` re-runs every cell; a cell folder left
half-written by a stopped run is refused by the planner until then). ``--record`` writes the table's numbers
(no run folders) for the docs. It also prints, per target and start (routing.ROUTE_STARTS), the share of 100 resets
(seeds 0-99) whose start already keeps every peg on its side.
"""
from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
from pathlib import Path

from diffdlo.tasks import task
from diffdlo.envs import BatchedShapeControl
from diffdlo.tasks.routing import ROUTE_STARTS
from diffdlo.planar.shapes import TargetError
from diffdlo.planar.params import load_params
from diffdlo.utils.files import check_fresh_file

PLANNERS = ("greedy", "cem", "gradient")
TARGETS = ("route", "route:hook_wrap", "route:zigzag_four")


def cell_dir(out: Path, planner: str, target: str, pin: int) -> Path:
    return out / f"{planner}-{target.split(':')[-1]}-pin{pin}"


def command(planner: str, target: str, pin: int, episodes: int, max_steps: int, folder: Path,
            overwrite: bool = False) -> list[str]:
    return [sys.executable, "-m", f"planners.{planner}", "--target", target, "--pin", str(pin), "--episodes",
            str(episodes), "--seed", "0", "--max-steps", str(max_steps), "--no-gif", "--out", str(folder),
            *(["--overwrite"] if overwrite else [])]


def start_sides(target: str, route_start: str, resets: int = 100) -> float:
    """The share of ``resets`` starts (seeds 0..resets-1) that already pass every peg on the route's side."""
    env = BatchedShapeControl(resets, target=target, reward="route_gain", route_start=route_start)
    env.reset(seed=0)
    return float(env.info()["sides_kept"].float().mean())


def summary(results: dict) -> dict:
    eps = results["episodes"]
    solved = [e for e in eps if e["success"]]
    return {"episodes": len(eps), "success": len(solved),
            "moves": sum(e["steps"] for e in solved) / len(solved) if solved else None,
            "final_error_cm": 100 * sum(e["final_error"] for e in eps) / len(eps),
            "wrong_side_at_end": sum(1 for e in eps if e.get("sides_kept") is False),
            "sim_evals_per_episode": results["sim_evals"] / len(eps), "plan_s_per_step": results["plan_s_per_step"],
            "wall_s": results["wall_s"],
            "steps": [e["steps"] for e in eps], "solved": [e["success"] for e in eps]}


def paired_pin(without: dict, with_pin: dict) -> dict:
    """Moves with the pin minus without, over the episodes both solved: mean and standard error; success counts."""
    diffs = [b - a for a, b, sa, sb in zip(without["steps"], with_pin["steps"], without["solved"], with_pin["solved"])
             if sa and sb]
    if not diffs:
        return {"pairs": 0}
    mean = sum(diffs) / len(diffs)
    se = (math.sqrt(sum((d - mean) ** 2 for d in diffs) / (len(diffs) - 1) / len(diffs)) if len(diffs) > 1
          else float("nan"))
    return {"pairs": len(diffs), "moves_delta": mean, "moves_delta_se": se,
            "success_delta": with_pin["success"] - without["success"]}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.studies.routing_planners", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True, help="the cells' folder")
    ap.add_argument("--episodes", type=int, default=20)
    ap.add_argument("--max-steps", type=int, default=40)
    ap.add_argument("--planners", nargs="+", default=list(PLANNERS), choices=PLANNERS)
    ap.add_argument("--targets", nargs="+", default=list(TARGETS))
    ap.add_argument("--rerun", action="store_true", help="re-run cells that have results (replacing them)")
    ap.add_argument("--record", type=Path, help="write the numbers to this JSON")
    ap.add_argument("--overwrite", action="store_true", help="replace an existing --record")
    args = ap.parse_args(argv)
    if args.episodes < 1 or args.max_steps < 1:
        ap.error(f"--episodes and --max-steps must be >= 1, got {args.episodes} and {args.max_steps}")
    for target in args.targets:
        try:
            if not task.is_route(target):
                raise TargetError("not a route ('route' or 'route:NAME')")
            task.resolve_target(target, load_params("cable"))
        except TargetError as exc:
            ap.error(f"--targets {target!r}: {exc}")
    try:
        if args.record is not None:
            check_fresh_file(args.record, args.overwrite)
    except FileExistsError as exc:
        print(exc, file=sys.stderr)
        return 2
    table: dict[str, dict] = {}
    cells = [(t, planner, pin) for t in args.targets for planner in args.planners for pin in (0, 1)]
    for i, (target, planner, pin) in enumerate(cells, 1):
        folder = cell_dir(args.out, planner, target, pin)
        results = folder / "results.json"
        if args.rerun or not results.exists():
            print(f"cell {i}/{len(cells)}: {planner} {target} pin {pin} -> {folder}", file=sys.stderr, flush=True)
            done = subprocess.run(command(planner, target, pin, args.episodes, args.max_steps, folder, args.rerun))
            if done.returncode != 0:
                print(f"cell {planner} {target} pin {pin} failed (exit {done.returncode}); the cells before it are "
                      f"kept: run the same command again to go on", file=sys.stderr)
                return done.returncode
        table[f"{planner} {target} pin{pin}"] = summary(json.loads(results.read_text()))
    print("| planner | target | pin | success | moves (solved) | final error [cm] | wrong side at the end | "
          "sim moves / episode | s / move | wall [s] | pin: moves vs none (paired) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for key, row in table.items():
        planner, target, pin = key.split()
        paired = ""
        if pin == "pin1":
            pp = paired_pin(table[f"{planner} {target} pin0"], row)
            row["pin_effect"] = pp
            paired = (f"{pp['moves_delta']:+.1f} ± {pp['moves_delta_se']:.1f} ({pp['pairs']} pairs)" if pp["pairs"]
                      else "no pair solved")
        moves = "-" if row["moves"] is None else f"{row['moves']:.1f}"
        print(f"| {planner} | {target} | {pin[3:]} | {row['success']}/{row['episodes']} | {moves} | "
              f"{row['final_error_cm']:.2f} | {row['wrong_side_at_end']} | {row['sim_evals_per_episode']:.0f} | "
              f"{row['plan_s_per_step']:.2f} | {row['wall_s']:.0f} | {paired} |")
    sides = {f"{t} {start}": start_sides(t, start) for t in args.targets for start in ROUTE_STARTS}
    print("\nStarts that already keep every peg on its side (100 resets, seeds 0-99): "
          + ", ".join(f"{k} {v:.0%}" for k, v in sides.items()))
    if args.record is not None:
        args.record.parent.mkdir(parents=True, exist_ok=True)
        args.record.write_text(json.dumps({"command": "python -m benchmarks.studies.routing_planners --out "
                                                      f"{args.out} --episodes {args.episodes} --max-steps "
                                                      f"{args.max_steps}", "cells": table,
                                           "starts_keeping_every_side": sides}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
