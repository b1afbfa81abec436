"""Comparison harness: greedy, CEM, gradient planner, SAC, PPO and PlaNet on the same tasks, several seeds each.

    python -m benchmarks.compare --quick                       # tiny grid, minutes: format example, not results
    python -m benchmarks.compare --methods cem sac --targets diagonal --seeds 0 1 --jobs 2
    python -m benchmarks.compare --report-only --report docs/RESULTS.md   # only (re)write the committed report

The grid (methods x variants x targets x seeds, with budgets) is data: benchmarks/compare.yaml (``full`` and
``quick``). Each cell runs the project's own entry point (``python -m planners.X`` / ``python -m agents.X``) as a
subprocess into ``<out>/<method>/<variant>/<target>/seed<s>/`` and is finished when its ``results.json`` exists:
finished cells are skipped, a learner cell with a ``checkpoint.pt`` but no ``results.json`` continues with
``--resume``, so a long comparison can be split over sessions. ``--jobs N`` runs N cells at once (subprocesses);
``--ray ADDRESS`` (``local`` for ``ray.init()``) runs them as Ray tasks instead (optional dependency).
One compare writes to an ``--out`` at a time (``<out>/.compare.lock``); stopping it (Ctrl-C, SIGTERM) stops its
cells' processes. cell.json records the settings a cell ran with: a finished cell whose grid entry changed since is
refused (``--rerun-changed`` reruns it into a fresh folder) and left out of the report.

The report (written to ``--report PATH``, default ``<out>/RESULTS.md``; figures in ``figures/`` beside it; the
committed one is ``--report docs/RESULTS.md``) only reads finished cells; its confidence intervals (stats.py, scipy):
a t-interval over seeds and a Wilson score interval over the pooled episodes.
Success at 1 cm: the episode terminated with shape_error < 0.01 m (the env's success). Success at 2 cm: the
episode's last shape_error < 2 cm; an episode ends at its first move under 1 cm or after max-steps moves, for
planners and learners alike, so this is "ended within 2 cm". Planners also get "moves to 2 cm" from their per-move
``errors`` (first move under 2 cm).

Modules: grid (the YAML, cells, command lines), runner (subprocesses, resume, Ray), processes (the cells'
process groups, stopping them), settings (a finished cell's settings against the grid's), stats (intervals, row
statistics), costs (planning against learning), report (the markdown), figures (matplotlib), arguments (options
and their checks), cli (main). Atomic writes and the lock are diffdlo/files.py's.
"""
from .cli import main
from .costs import PAYBACK_SLACK, cost_section, payback, row_cost
from .figures import make_cost_figures, make_figures
from .grid import GRID_FILE, NAMED, ROOT, build_cells, cell_dir, command_line, is_done, load_grid
from .report import COLUMNS, harness_command, machine_label, task_groups, write_report
from .runner import machine_info, merge_subruns, random_target_names, run_cell, run_cells
from .settings import argv_changes, changed_cells, comparable_argv, settings_changes
from .stats import row_stats, t_interval, t_quantile, wilson

__all__ = ["COLUMNS", "GRID_FILE", "NAMED", "PAYBACK_SLACK", "ROOT", "argv_changes", "build_cells", "cell_dir",
           "changed_cells", "command_line", "comparable_argv", "cost_section", "harness_command", "is_done",
           "load_grid", "machine_info", "machine_label", "main", "make_cost_figures", "make_figures", "merge_subruns",
           "payback", "random_target_names", "row_cost", "row_stats", "run_cell", "run_cells", "settings_changes",
           "t_interval", "t_quantile", "task_groups", "wilson", "write_report"]
