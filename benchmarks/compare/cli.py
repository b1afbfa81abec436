"""The command line: ``python -m benchmarks.compare`` selects cells of the grid, runs them, writes the report.

A run holds ``<out>/.compare.lock`` (one writer per cell root), stops its cells' processes when it is stopped
(Ctrl-C, SIGTERM, SIGHUP), refuses finished cells whose grid settings changed unless --rerun-changed, and writes
the report only where --report names (default ``<out>/RESULTS.md``, figures beside it in ``figures/``)."""
from __future__ import annotations

import sys
from pathlib import Path

from . import __doc__ as HARNESS_DOC
from .arguments import filter_errors, option_errors, parser, select_rows
from .grid import build_cells, command_line, is_done, load_grid
from diffdlo.utils.files import OutBusyError, out_lock
from .processes import Terminated, signals_stop_compare
from .records import RESULTS_FILE, collect, read_records, record_changes, record_key
from .grid import ROOT
from .report import readme_summary, update_readme, write_report
from .runner import run_cells
from .settings import changed_cells, describe_changes, supersede

EXIT_INTERRUPTED = 130          # as a shell reports a command ended by Ctrl-C
EXIT_TERMINATED = 143           # ... and by SIGTERM


def _say(message: str) -> None:
    print(f"compare: {message}", file=sys.stderr, flush=True)


def _changed_settings(cells: list, out: Path, rerun: bool) -> bool:
    """Finished cells whose grid settings changed: moved aside to rerun (``rerun``) or named. False: refuse."""
    changed = changed_cells(cells)
    if not changed:
        return True
    if not rerun:
        _say(f"{len(changed)} finished cell(s) ran with other settings than the grid's now; rerun them with "
             "--rerun-changed (their folders are moved to <out>/superseded/), or restore the grid:")
        for c, ch in changed:
            print(f"  {describe_changes(c, ch)}", file=sys.stderr)
        return False
    for c, ch in changed:
        _say(f"rerunning {describe_changes(c, ch)}; the old folder is now {supersede(c, out)}")
    return True


def _run(args, cells, out: Path) -> int:
    """Run the selected cells under the lock of ``out``. Returns the exit status."""
    try:
        with out_lock(out, ".compare.lock", "another compare"), signals_stop_compare():
            if not _changed_settings(cells, out, args.rerun_changed):
                return 2
            results = run_cells(cells, jobs=args.jobs, ray_address=args.ray, progress=not args.no_progress,
                                ray_num_cpus=args.ray_cpus)
    except OutBusyError as exc:
        _say(str(exc))
        return 3
    except KeyboardInterrupt as exc:
        _say("stopped: no report written; finished cells are kept and the rest run next time")
        return EXIT_TERMINATED if isinstance(exc, Terminated) else EXIT_INTERRUPTED
    counts = {s: sum(r["status"] == s for r in results) for s in ("done", "skipped", "failed")}
    print(f"cells: {counts['done']} run, {counts['skipped']} already finished (skipped), {counts['failed']} failed")
    return 1 if counts["failed"] else 0


def _without_recorded(cells: list, results_file: Path) -> list:
    """``cells`` less those with a record in ``results_file`` made with the grid's settings now (their folder may
    be gone: the record is their result). A cell whose folder has results stays, as run_cells skips it anyway."""
    records = {record_key(r): r for r in read_records(results_file)}
    keep = [c for c in cells if is_done(c) or (rec := records.get(record_key(c))) is None or record_changes(rec, c)]
    if len(keep) < len(cells):
        _say(f"{len(cells) - len(keep)} cell(s) recorded in {results_file} with the grid's settings are skipped "
             "(--skip-recorded)")
    return keep


def _finished(cell) -> tuple[dict, dict]:
    """A finished cell's results.json and cell.json (empty if it has none)."""
    import json

    from .grid import cell_dir
    meta = cell_dir(cell) / "cell.json"
    return (json.loads((cell_dir(cell) / "results.json").read_text()),
            json.loads(meta.read_text()) if meta.exists() else {})


def _rebuild_command(results_file: Path, doc: Path) -> str:
    """The command that rebuilds this report from its results file (the defaults left out)."""
    import shlex
    argv = ["python", "-m", "benchmarks.compare", "--report-only"]
    if results_file.resolve() != RESULTS_FILE.resolve():
        argv += ["--results", str(results_file)]
    if doc != Path("docs/RESULTS.md"):
        argv += ["--report", str(doc)]
    return shlex.join(argv)


def main(argv: list[str] | None = None) -> int:
    ap = parser(HARNESS_DOC.split("\n\n")[0])
    args = ap.parse_args(argv)
    grid = load_grid(args.quick, args.grid)
    out = Path(args.out or ("runs/compare-quick" if args.quick else "runs/compare"))
    errors = filter_errors(args, grid) + option_errors(args)
    if errors:
        ap.error("; ".join(errors))
    cells = select_rows(build_cells(grid, out, args.methods, args.variants, args.targets, args.seeds,
                                    args.learner_device), args.rows)
    if not cells:
        ap.error("no cell matches the filters")
    results_file = Path(args.results) if args.results else RESULTS_FILE
    if args.skip_recorded:
        try:
            cells = _without_recorded(cells, results_file)
        except (OSError, ValueError) as exc:
            ap.error(f"--results {results_file}: {exc}")
    from_records = args.collect or (args.report_only and args.out is None and not args.quick)
    if from_records:
        try:
            if args.collect:
                n, total = collect([(c, *_finished(c)) for c in cells if is_done(c)], results_file)
                print(f"collect: {n} finished cell(s) of {out} -> {results_file} ({total} records)")
            records = read_records(results_file)
        except (OSError, ValueError) as exc:
            ap.error(f"--results {results_file}: {exc}")
        doc = Path(args.report) if args.report else Path("docs/RESULTS.md")
        every_cell = build_cells(grid, out)
        write_report(grid, out, doc, None if args.no_figures else doc.parent / "figures", every_cell,
                     records=records, source=_rebuild_command(results_file, doc))
        print(f"report: {doc} (from {results_file})")
        if doc.resolve() == (ROOT / "docs" / "RESULTS.md").resolve() and grid.get("main"):
            if update_readme(ROOT / "README.md", readme_summary(grid, records, every_cell)):
                print("report: README.md summary block")
        return 0
    if args.list:
        for c in cells:
            print(("done    " if is_done(c) else "todo    ") + command_line(c))
        return 0
    status = 0
    if not args.report_only:
        status = _run(args, cells, out)
        if status not in (0, 1):
            return status
    if not args.no_report:
        doc = Path(args.report) if args.report else out / "RESULTS.md"
        every_cell = build_cells(grid, out)
        left_out = changed_cells(every_cell)
        if left_out:
            _say(f"the report leaves out {len(left_out)} finished cell(s) whose grid settings changed since they ran "
                 "(named at its top; --rerun-changed reruns them)")
        write_report(grid, out, doc, None if args.no_figures else doc.parent / "figures", every_cell)
        print(f"report: {doc}")
    return status
