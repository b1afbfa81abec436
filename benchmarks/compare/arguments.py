"""The command line's options and their checks: a misspelled filter or a count below 1 is an error (exit code 2)
on one line that names the bad value and what is allowed, never a filter silently dropped."""
from __future__ import annotations

import argparse
import os
from typing import Any, NoReturn

from .grid import GRID_FILE


class OneLineParser(argparse.ArgumentParser):
    """Errors as one line on stderr ("python -m benchmarks.compare: error: ..."), exit code 2."""

    def error(self, message: str) -> NoReturn:
        if message.startswith("argument --report: expected one argument"):
            message += " (--report PATH names where the report goes; to only write it: --report-only)"
        self.exit(2, f"{self.prog}: error: {message} (see --help)\n")


def positive_int(text: str) -> int:
    """A count of at least 1."""
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a whole number of at least 1, got {text!r}") from None
    if n < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {n}")
    return n


def parser(description: str) -> OneLineParser:
    ap = OneLineParser(prog="python -m benchmarks.compare", description=description,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="the tiny grid (minutes): a format example, not results")
    ap.add_argument("--grid", default=str(GRID_FILE), help="grid YAML (default benchmarks/compare.yaml)")
    ap.add_argument("--methods", nargs="+", default=None)
    ap.add_argument("--variants", nargs="+", default=None)
    ap.add_argument("--targets", nargs="+", default=None)
    ap.add_argument("--seeds", nargs="+", type=int, default=None)
    ap.add_argument("--rows", nargs="+", default=None, metavar="METHOD/VARIANT",
                    help="only these rows, their cells run in this order (the other filters still apply): one "
                         "invocation for several rows keeps every job busy until the last cell")
    ap.add_argument("--out", default=None, help="cell root (default runs/compare; --quick: runs/compare-quick)")
    ap.add_argument("--jobs", type=positive_int, default=os.cpu_count() or 1,
                    help="cells at once, at least 1 (default: cores)")
    ap.add_argument("--ray", default=None, metavar="ADDRESS", help="run cells as Ray tasks ('local': ray.init())")
    ap.add_argument("--ray-cpus", type=positive_int, default=None, metavar="N",
                    help="with --ray local: the CPUs the local Ray offers (default: all)")
    ap.add_argument("--report", default=None, metavar="PATH",
                    help="write the report to PATH, its figures into PATH's folder/figures (default: "
                         "<out>/RESULTS.md; the committed one: --report docs/RESULTS.md)")
    ap.add_argument("--report-only", action="store_true",
                    help="run nothing, only write the report: from the results file (--results) when --out is not "
                         "given (then to docs/RESULTS.md), else from the finished cells under --out")
    ap.add_argument("--collect", action="store_true",
                    help="add the finished cells under --out to the results file (--results), replacing their "
                         "records, then write the report from that file (default docs/RESULTS.md)")
    ap.add_argument("--results", default=None, metavar="FILE",
                    help="the cells' records, one JSON line per cell (default docs/results/cells.jsonl)")
    ap.add_argument("--no-report", action="store_true", help="run cells, write no report")
    ap.add_argument("--no-figures", action="store_true", help="write the report without figures")
    ap.add_argument("--rerun-changed", action="store_true",
                    help="rerun finished cells whose settings in the grid changed since they ran (their old folder "
                         "is moved to <out>/superseded/); without it such cells stop the run")
    ap.add_argument("--skip-recorded", action="store_true",
                    help="also skip cells that have a record in the results file (--results) made with the grid's "
                         "settings now, though their run folder is gone (a grid continued on a new machine from the "
                         "committed docs/results/cells.jsonl); without it such cells run again, as a reproduction")
    ap.add_argument("--list", action="store_true", help="print the selected cells and their commands, run nothing")
    ap.add_argument("--no-progress", action="store_true")
    ap.add_argument("--learner-device", default=None, metavar="DEVICE",
                    help="learners' networks on DEVICE (e.g. cuda), simulation on the CPU; planners unchanged")
    return ap


def _unknown(flag: str, bad: list, allowed: list, scope: str = "this grid has") -> str:
    return (f"{flag}: unknown {', '.join(map(repr, bad))}; {scope}: {', '.join(map(str, allowed))}")


def filter_errors(args: argparse.Namespace, grid: dict[str, Any]) -> list[str]:
    """Each filter value the grid does not have, as a message naming it and the allowed ones."""
    errors = []
    methods = list(grid["methods"])
    for flag, vals, allowed in (("--methods", args.methods, methods), ("--targets", args.targets, grid["targets"]),
                                ("--seeds", args.seeds, grid["seeds"])):
        bad = [v for v in vals or [] if v not in allowed]
        if bad:
            errors.append(_unknown(flag, bad, allowed))
    chosen = [m for m in args.methods or [] if m in grid["methods"]] or methods
    variants = list(dict.fromkeys(v for m in chosen for v in grid["methods"][m]["variants"]))
    bad = [v for v in args.variants or [] if v not in variants]
    if bad:
        scope = f"the methods {' '.join(chosen)} have" if chosen != methods else "this grid has"
        errors.append(_unknown("--variants", bad, variants, scope))
    for row in args.rows or []:
        method, _, variant = row.partition("/")
        if method not in grid["methods"] or variant not in grid["methods"][method]["variants"]:
            known = [f"{m}/{v}" for m, spec in grid["methods"].items() for v in spec["variants"]]
            errors.append(_unknown("--rows", [row], known, "this grid has the rows"))
    return errors


def select_rows(cells: list[dict[str, Any]], rows: list[str] | None) -> list[dict[str, Any]]:
    """The cells of ``rows`` (METHOD/VARIANT), ordered as the rows are (each row's cells in their own order); all
    cells when ``rows`` is None."""
    if rows is None:
        return cells
    order = {row: i for i, row in enumerate(dict.fromkeys(rows))}
    chosen = [c for c in cells if f"{c['method']}/{c['variant']}" in order]
    return sorted(chosen, key=lambda c: order[f"{c['method']}/{c['variant']}"])


def option_errors(args: argparse.Namespace) -> list[str]:
    """Options that do not go together."""
    errors = []
    if args.report_only and args.no_report:
        errors.append("--report-only and --no-report: nothing to do")
    if args.no_report and args.report:
        errors.append(f"--report {args.report} and --no-report: choose one")
    if args.ray_cpus is not None and args.ray != "local":
        errors.append("--ray-cpus: only with --ray local (a running cluster has its own CPUs)")
    if args.rerun_changed and (args.report_only or args.list or args.collect):
        errors.append("--rerun-changed: only when running cells (not with --report-only, --collect or --list)")
    if args.skip_recorded and (args.report_only or args.collect):
        errors.append("--skip-recorded: only when running or listing cells (not with --report-only or --collect)")
    if args.collect and (args.list or args.no_report):
        errors.append("--collect writes the results file and the report: not with --list or --no-report")
    if args.collect and args.out is None:
        errors.append("--collect: name the run folder to collect from with --out")
    return errors
