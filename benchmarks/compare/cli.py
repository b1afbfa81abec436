"""The command line: ``python -m benchmarks.compare`` selects cells of the grid, runs them, writes the report."""
from __future__ import annotations

import argparse
import os
from pathlib import Path

from . import __doc__ as HARNESS_DOC
from .grid import GRID_FILE, build_cells, command_line, is_done, load_grid
from .report import write_report
from .runner import run_cells


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.compare", description=HARNESS_DOC.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="the tiny grid (minutes): a format example, not results")
    ap.add_argument("--grid", default=str(GRID_FILE), help="grid YAML (default benchmarks/compare.yaml)")
    ap.add_argument("--methods", nargs="+", default=None)
    ap.add_argument("--variants", nargs="+", default=None)
    ap.add_argument("--targets", nargs="+", default=None)
    ap.add_argument("--seeds", nargs="+", type=int, default=None)
    ap.add_argument("--out", default=None, help="cell root (default runs/compare; --quick: runs/compare-quick)")
    ap.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="cells at once (default: cores)")
    ap.add_argument("--ray", default=None, metavar="ADDRESS", help="run cells as Ray tasks ('local': ray.init())")
    ap.add_argument("--report", action="store_true", help="only write the report from finished cells")
    ap.add_argument("--no-report", action="store_true", help="run cells, write no report")
    ap.add_argument("--doc", default="docs/RESULTS.md", help="report path (default docs/RESULTS.md)")
    ap.add_argument("--figures", default="docs/figures", help="figure folder ('' for none)")
    ap.add_argument("--list", action="store_true", help="print the selected cells and their commands, run nothing")
    ap.add_argument("--no-progress", action="store_true")
    ap.add_argument("--learner-device", default=None, metavar="DEVICE",
                    help="learners' networks on DEVICE (e.g. cuda), simulation on the CPU; planners unchanged")
    args = ap.parse_args(argv)
    grid = load_grid(args.quick, args.grid)
    out = Path(args.out or ("runs/compare-quick" if args.quick else "runs/compare"))
    for name, vals, allowed in (("--methods", args.methods, list(grid["methods"])),
                                ("--targets", args.targets, grid["targets"])):
        bad = sorted(set(vals or []) - set(allowed))
        if bad:
            ap.error(f"{name}: unknown {bad}; this grid has {allowed}")
    cells = build_cells(grid, out, args.methods, args.variants, args.targets, args.seeds, args.learner_device)
    if not cells:
        ap.error("no cell matches the filters")
    if args.list:
        for c in cells:
            print(("done    " if is_done(c) else "todo    ") + command_line(c))
        return 0
    status = 0
    if not args.report:
        results = run_cells(cells, jobs=args.jobs, ray_address=args.ray, progress=not args.no_progress)
        counts = {s: sum(r["status"] == s for r in results) for s in ("done", "skipped", "failed")}
        print(f"cells: {counts['done']} run, {counts['skipped']} already finished (skipped), {counts['failed']} failed")
        status = 1 if counts["failed"] else 0
    if not args.no_report:
        write_report(grid, out, args.doc, args.figures or None, build_cells(grid, out))
        print(f"report: {args.doc}")
    return status

