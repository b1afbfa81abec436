"""The 3-D two-gripper task's grid (docs/CABLE3D.md): a planner, closed loop, on every cable, seeds x episodes.

    python -m benchmarks.cable3d_grid --run --out runs/cable3d20                  # CEM, 5 cables x 5 seeds x 20
    python -m benchmarks.cable3d_grid --run --out runs/cable3d20 --cables DLO3 DLO1 &   # or two at once, one core
    python -m benchmarks.cable3d_grid --run --out runs/cable3d20 --cables DLO2 DLO4 DLO5  # each
    python -m benchmarks.cable3d_grid --collect runs/cable3d20 --record docs/results/cable3d_cem_grid.json
    python -m benchmarks.cable3d_grid --run --out runs/standin20 --cables DLO3 --tag closed-physics \
        -- --stand-in runs/real_cable_residual/DLO3_residual.pt     # flags after -- go to every cell's planner

``--run`` runs ``python -m planners.cable3d`` once per cable and seed (seed s: the episodes reset with seeds
1000 s ... 1000 s + episodes - 1, so no two seeds share an episode), each cell in its own folder
OUT/<tag>-<cable>-s<s> (the tag: ``--tag``, by default the planner's name), a cell with a results.json already
there skipped (run it again to finish a grid).
``--collect`` reads the cells, prints the table (success, moves to success, final error, planning time) and writes
the record (per cell: its success, moves and errors per episode; no shapes) where ``--record`` says.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

from diffdlo.chain3d.cables import cable_names
from diffdlo.utils.files import write_json_atomic


def cell(out: Path, tag: str, cable: str, seed: int) -> Path:
    return out / f"{tag}-{cable}-s{seed}"


def run(out: Path, planner: str, cables: list[str], seeds: list[int], episodes: int, threads: int = 1,
        tag: str | None = None, flags: list[str] = ()) -> int:
    for cable in cables:
        for s in seeds:
            folder = cell(out, tag or planner, cable, s)
            if (folder / "results.json").is_file():
                continue
            argv = [sys.executable, "-m", "planners.cable3d", "--planner", planner, "--cable", cable,
                    "--episodes", str(episodes), "--seed", str(1000 * s), "--threads", str(threads),
                    "--out", str(folder), "--overwrite", "--quiet", *flags]
            code = subprocess.run(argv).returncode
            if code:
                return code
    return 0


def collect(out: Path, record: Path | None) -> int:
    cells = sorted(p for p in out.glob("*-s*") if (p / "results.json").is_file())
    if not cells:
        print(f"no finished cells under {out}", file=sys.stderr)
        return 2
    rows: dict[str, list[dict]] = {}
    for folder in cells:
        d = json.loads((folder / "results.json").read_text())
        tag = folder.name.rsplit(f"-{d['cable']}-s", 1)[0]
        key = f"{tag} {d['cable']}"
        rows.setdefault(key, []).append({
            "cell": folder.name, "argv": d["argv"], "options": d.get("options"),
            "plan_seconds_per_move": d["plan_seconds_per_move"], "sim_moves_per_episode": d["sim_moves_per_episode"],
            "episodes": [{"seed": e["seed"], "success": e["success"], "steps": e["steps"],
                          "final_error_cm": round(100 * e["errors"][-1], 3),
                          "final_worst_error_cm": round(100 * e["worst_errors"][-1], 3)} for e in d["episode_records"]]})
    print("| cell, cable | seeds x episodes | success | moves to success (mean) | final mean error [cm] "
          "(median / max) | planning s / move |\n|---|---|---|---|---|---|")
    for key, seeds in rows.items():
        eps = [e for s in seeds for e in s["episodes"]]
        solved = [e for e in eps if e["success"]]
        finals = sorted(e["final_error_cm"] for e in eps)
        moves = f"{sum(e['steps'] for e in solved) / len(solved):.1f}" if solved else "-"
        plan = sum(s["plan_seconds_per_move"] for s in seeds) / len(seeds)
        print(f"| {key} | {len(seeds)} x {len(eps) // len(seeds)} | {100 * len(solved) / len(eps):.0f} % | {moves} | "
              f"{finals[len(finals) // 2]:.2f} / {finals[-1]:.2f} | {plan:.2f} |")
    if record is not None:
        write_json_atomic(record, {"command": "python -m benchmarks.cable3d_grid --run --out OUT, then --collect OUT",
                                   "rows": rows})
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.cable3d_grid", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", action="store_true")
    ap.add_argument("--collect", type=Path, help="a grid's folder to read")
    ap.add_argument("--out", type=Path, default=Path("runs/cable3d20"))
    ap.add_argument("--record", type=Path, help="with --collect: write the record here")
    ap.add_argument("--planner", choices=("cem", "gradient"), default="cem")
    ap.add_argument("--cables", nargs="+", default=cable_names(), choices=cable_names())
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    ap.add_argument("--episodes", type=int, default=20)
    ap.add_argument("--tag", default=None, help="the cells' name (default: the planner's)")
    ap.add_argument("--threads", type=int, default=1, help="torch threads of each cell (run two grids side by side "
                                                           "on two cores, each on its own --cables)")
    argv = sys.argv[1:] if argv is None else list(argv)
    flags = argv[argv.index("--") + 1:] if "--" in argv else []
    args = ap.parse_args(argv[:argv.index("--")] if "--" in argv else argv)
    if flags and not args.run:
        ap.error(f"planner flags after -- need --run, got {flags}")
    if args.run == (args.collect is not None):
        ap.error("give one of --run or --collect DIR")
    if args.episodes < 1 or min(args.seeds) < 0 or args.threads < 1:
        ap.error(f"--episodes and --threads must be >= 1 and --seeds >= 0, got {args.episodes}, {args.threads} and "
                 f"{args.seeds}")
    if args.run:
        return run(args.out, args.planner, args.cables, args.seeds, args.episodes, args.threads, args.tag, flags)
    return collect(args.collect, args.record)


if __name__ == "__main__":
    sys.exit(main())
