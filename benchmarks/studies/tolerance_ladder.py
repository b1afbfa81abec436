"""A trained learner's success against tolerance, exact at every rung: its checkpoint re-evaluated until a tight one.

    python -m benchmarks.studies.tolerance_ladder RUN_DIR [RUN_DIR ...] [--until 0.002] --out DIR

A learner's precision cell (compare.yaml's `precise` rows) runs its episodes until its own 5 mm success, so the
report's 2 mm point for it is only a lower bound (benchmarks/compare/precision.py). Here each run's final checkpoint
acts again, as in its final evaluation (`python -m agents.tools.evaluate`: deterministic, the run's eval episodes
and eval seed, so the same start ropes as the comparison's paired episodes; by policy rollouts when the run's final
evaluation used them), but until a mean error of --until (the worst node's tolerance kept as the run's). Every
episode then holds each looser tolerance's answer exactly, and the ladder (2 cm, 1 cm, 5 mm, 2 mm mean; the
report's, read by the report's own `precision.point`) has no lower bounds left, unless a tolerance tighter than
--until is asked for.

A world model planning with CEM (PlaNet's) and a policy (SAC, PPO, acting alone) choose their moves without looking
at the tolerance, so each episode holds the answer at every looser rung exactly. They are the run's final-evaluation
episodes continued where the run evaluated only at its end; a run that evaluated before (the comparison's cells
do) had moved its planner's CEM generators on, so the moves differ from its final evaluation's, and the looser
rungs read a second sample of the same policy from the same start ropes. A policy acting by rollouts scores its
candidates by their moves to success, which depend on the tolerance: its episodes are its own at --until.

Runs named .../seedN are pooled by their parent folder (e.g. the comparison's runs/compare/pets/precise/random).
Writes each evaluation to <out>/<group>/seedN/ and the table to <out>/results.json.
"""
from __future__ import annotations

import argparse
import math
import re
import sys
from pathlib import Path
from typing import Any

from agents.tools import evaluate as evaluate_cli
from agents.tools.policy import load_policy
from benchmarks.compare.precision import LADDER, _share, length, point
from diffdlo.utils.files import check_fresh_out, out_lock, write_json_atomic


def group_of(run: Path) -> tuple[str, str]:
    """(group, member) names of a run folder: its parent and 'seedN' for .../seedN, else the folder itself."""
    run = Path(run)
    if re.fullmatch(r"seed\d+", run.name):
        return run.parent.as_posix(), run.name
    return run.as_posix(), "run"


def evaluate_until(run: Path, until: float, out: Path, overwrite: bool) -> list[dict[str, Any]]:
    """The run's final-evaluation episodes re-run until a mean error of ``until`` [m]: their records."""
    import json
    cfg = load_policy(run).config
    argv = [str(run), "--success-tol", repr(until), "--no-gif", "--out", str(out)]
    if cfg.run.rollout_candidates:
        argv += ["--rollouts", str(cfg.run.rollout_candidates), "--rollout-moves", str(cfg.run.rollout_moves)]
    if overwrite:
        argv.append("--overwrite")
    if evaluate_cli.main(argv) != 0:
        raise RuntimeError(f"{run}: its evaluation failed (its message is above)")
    return json.loads((out / "results.json").read_text())["episodes"]


def ladder_table(groups: dict[str, list[list[dict]]], until: float) -> tuple[str, list[dict[str, Any]]]:
    rungs = sorted(set(LADDER) | {until}, reverse=True)
    head = "| runs | seeds · episodes | " + " | ".join(f"< {length(t)}" for t in rungs) + " |"
    lines = [head, "|---|---|" + "---|" * len(rungs)]
    rows = []
    for name, runs in groups.items():
        points = [point(runs, t) for t in rungs]
        lines.append(f"| {name} | {len(runs)} · {sum(map(len, runs))} | " + " | ".join(map(_share, points)) + " |")
        rows.append({"group": name, "seeds": len(runs), "ladder": [
            {"tol": t, "success": p["solved"] / p["episodes"], "moves": p["moves"], "lower_bound": bool(p["censored"])}
            for t, p in zip(rungs, points)]})
    return "\n".join(lines), rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.studies.tolerance_ladder",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", type=Path, help="learner run folders (each with its checkpoint.pt)")
    ap.add_argument("--until", type=float, default=0.002, help="the mean error [m] the episodes run until")
    ap.add_argument("--out", type=Path, required=True, help="folder for the evaluations and results.json")
    ap.add_argument("--overwrite", action="store_true", help="replace earlier evaluations in --out")
    args = ap.parse_args(argv)
    if not (math.isfinite(args.until) and args.until > 0):
        ap.error(f"--until must be a positive number [m], got {args.until}")
    names = [group_of(r) for r in args.runs]
    if len(set(names)) < len(names):
        ap.error(f"a run is given twice: {[str(r) for r, n in zip(args.runs, names) if names.count(n) > 1]}")
    try:
        check_fresh_out(args.out, args.overwrite, what="a tolerance_ladder run")
        with out_lock(args.out):
            groups: dict[str, list[list[dict]]] = {}
            for run, (group, member) in zip(args.runs, names):
                sub = args.out / group.strip("/").replace("/", "_") / member
                groups.setdefault(group, []).append(evaluate_until(run, args.until, sub, args.overwrite))
            text, rows = ladder_table(groups, args.until)
            write_json_atomic(args.out / "results.json", {"until": args.until, "rows": rows,
                                                          "runs": [str(r) for r in args.runs]})
    except (ValueError, FileNotFoundError, FileExistsError, RuntimeError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"success · mean moves of the episodes within, each run's eval episodes run until {length(args.until)}:")
    print(text)
    print(f"wrote {args.out / 'results.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
