"""Comparison harness: greedy, CEM, the gradient planner, SAC, PPO, the PETS-style world model, PlaNet's RSSM and
APG on the same tasks and the same episodes, several seeds each.

    python -m benchmarks.compare --quick                       # tiny grid, minutes: format example, not results
    python -m benchmarks.compare --methods cem sac --targets random --seeds 0 1 --jobs 2
    python -m benchmarks.compare --rows pets/tuned sac/tuned --jobs 2   # these rows, in this order, one job pool
    python -m benchmarks.compare --collect --out runs/compare  # finished cells -> docs/results/cells.jsonl + report
    python -m benchmarks.compare --report-only                 # rebuild docs/RESULTS.md from the committed records

The grid (methods x variants x targets x seeds, with budgets) is data: benchmarks/compare.yaml (``full`` and
``quick``). Each cell runs the project's own entry point (``python -m planners.X`` / ``python -m agents.X``) as a
subprocess into ``<out>/<method>/<variant>/<target>/seed<s>/`` and is finished when its ``results.json`` exists:
finished cells are skipped, a learner cell with a ``checkpoint.pt`` but no ``results.json`` continues with
``--resume``, so a long comparison can be split over sessions on one machine; on a new one, ``--skip-recorded``
also skips the cells the results file records with the grid's settings now. ``--jobs N`` runs N cells at once
(subprocesses); ``--ray ADDRESS`` (``local`` for ``ray.init()``) runs them as Ray tasks instead (optional dependency).
One compare writes to an ``--out`` at a time (``<out>/.compare.lock``); stopping it (Ctrl-C, SIGTERM) stops its
cells' processes. cell.json records the settings a cell ran with: a finished cell whose grid entry changed since is
refused (``--rerun-changed`` reruns it into a fresh folder) and left out of the report.

Episode i of seed s is one rope's ``env.reset(seed=eval_seed_base + 1000 s + i)`` for every method, so rows are
compared episode by episode (summary.py pairs them, checking each episode's start error and target).
The results travel with the code: ``--collect`` writes each finished cell's record (records.py: its command,
settings, costs and per-episode outcomes) into ``docs/results/cells.jsonl``, from which ``--report-only`` rebuilds
``docs/RESULTS.md`` and its figures without the run folders. A report from run folders goes to ``--report PATH``
(default ``<out>/RESULTS.md``; figures in ``figures/`` beside it). Its confidence intervals (stats.py, scipy): a
t-interval over seeds and a Wilson score interval over the pooled episodes; paired t-intervals against CEM.
Success at 1 cm: the episode terminated with shape_error < 0.01 m (the env's success). Success at 2 cm: the
episode's last shape_error < 2 cm; an episode ends at its first move under 1 cm or after max-steps moves, for
planners and learners alike, so this is "ended within 2 cm". Records with per-move ``errors`` (planners; learners'
since they keep them) also get "moves to 2 cm" (the first move under 2 cm).

Modules: grid (the YAML, cells, command lines), runner (subprocesses, resume, Ray), processes (the cells'
process groups, stopping them), settings (a finished cell's settings against the grid's), records (the committed
results), stats (intervals, row statistics), summary (the main table, pairing, missing cells and their cost),
precision (the rows that declare a task ``tolerance``: success at it and at a ladder of tolerances, from the
episodes' recorded errors), costs (planning against learning), report (the markdown), figures (matplotlib), arguments
(options and their checks), cli (main). Atomic writes and the lock are diffdlo/utils/files.py's.
"""
from .cli import main
from .costs import PAYBACK_SLACK, cost_section, payback, row_cost
from .figures import make_cost_figures, make_figures
from .grid import (GRID_FILE, NAMED, ROOT, build_cells, cell_dir, command_line, is_done, load_grid, main_rows,
                   method_label)
from .records import RESULTS_FILE, collect, read_records, write_records
from .report import COLUMNS, harness_command, machine_label, task_groups, write_report
from .runner import machine_info, run_cell, run_cells
from .settings import argv_changes, changed_cells, comparable_argv, settings_changes
from .stats import row_stats, success_move, t_interval, t_quantile, wilson

__all__ = ["COLUMNS", "GRID_FILE", "RESULTS_FILE", "collect", "read_records", "write_records", "NAMED", "PAYBACK_SLACK", "ROOT", "argv_changes", "build_cells", "cell_dir",
           "changed_cells", "command_line", "comparable_argv", "cost_section", "harness_command", "is_done",
           "load_grid", "machine_info", "main_rows", "method_label", "machine_label", "main", "make_cost_figures", "make_figures", "payback",
           "row_cost", "row_stats", "run_cell", "run_cells", "settings_changes", "success_move",
           "t_interval", "t_quantile", "task_groups", "wilson", "write_report"]
