"""The planners on routes among pegs (docs/ROUTING.md): greedy, CEM and the gradient planner on random routes and
the held-out layouts, with and without the pin, on the same episodes (seed 0 + i: the same board and start for
every planner), and the pin's effect paired episode by episode.

    python -m benchmarks.studies.routing_planners --out runs/routing                 # runs what is missing, prints
    python -m benchmarks.studies.routing_planners --out runs/routing --record docs/results/routing_planners.json

Each cell is one planner command (``python -m planners.<planner> --target T --pin P --episodes E --seed 0
--max-steps 40``) into OUT/<planner>-<target>-pin<P>; a cell whose results.json exists is read, not re-run
(``--overwrite`` re-runs). ``--record`` writes the table's numbers (no run folders) for the docs.
"""
from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
from pathlib import Path

from diffdlo.utils.files import check_fresh_file

PLANNERS = ("greedy", "cem", "gradient")
TARGETS = ("route", "route:hook_wrap", "route:zigzag_four")


def cell_dir(out: Path, planner: str, target: str, pin: int) -> Path:
    return out / f"{planner}-{target.split(':')[-1]}-pin{pin}"


def command(planner: str, target: str, pin: int, episodes: int, max_steps: int, folder: Path) -> list[str]:
    return [sys.executable, "-m", f"planners.{planner}", "--target", target, "--pin", str(pin), "--episodes",
            str(episodes), "--seed", "0", "--max-steps", str(max_steps), "--quiet", "--no-gif", "--overwrite",
            "--out", str(folder)]


def summary(results: dict) -> dict:
    eps = results["episodes"]
    solved = [e for e in eps if e["success"]]
    return {"episodes": len(eps), "success": len(solved),
            "moves": sum(e["steps"] for e in solved) / len(solved) if solved else None,
            "final_error_cm": 100 * sum(e["final_error"] for e in eps) / len(eps),
            "wrong_side_at_end": sum(1 for e in eps if e.get("sides_kept") is False),
            "sim_evals_per_episode": results["sim_evals"] / len(eps), "plan_s_per_step": results["plan_s_per_step"],
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
    ap.add_argument("--overwrite", action="store_true", help="re-run cells that have results")
    ap.add_argument("--record", type=Path, help="write the numbers to this JSON (refuses an existing one without "
                                                "--overwrite)")
    args = ap.parse_args(argv)
    if args.episodes < 1 or args.max_steps < 1:
        ap.error(f"--episodes and --max-steps must be >= 1, got {args.episodes} and {args.max_steps}")
    try:
        if args.record is not None:
            check_fresh_file(args.record, args.overwrite)
    except FileExistsError as exc:
        print(exc, file=sys.stderr)
        return 2
    table: dict[str, dict] = {}
    for target in args.targets:
        for planner in args.planners:
            for pin in (0, 1):
                folder = cell_dir(args.out, planner, target, pin)
                results = folder / "results.json"
                if args.overwrite or not results.exists():
                    subprocess.run(command(planner, target, pin, args.episodes, args.max_steps, folder), check=True)
                table[f"{planner} {target} pin{pin}"] = summary(json.loads(results.read_text()))
    print("| planner | target | pin | success | moves (solved) | final error [cm] | wrong side at the end | "
          "sim moves / episode | s / move | pin: moves vs none (paired) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
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
              f"{row['plan_s_per_step']:.2f} | {paired} |")
    if args.record is not None:
        args.record.parent.mkdir(parents=True, exist_ok=True)
        args.record.write_text(json.dumps({"command": "python -m benchmarks.studies.routing_planners --out "
                                                      f"{args.out} --episodes {args.episodes} --max-steps "
                                                      f"{args.max_steps}", "cells": table}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
