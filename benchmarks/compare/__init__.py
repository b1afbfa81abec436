"""Comparison harness: greedy, CEM, gradient planner, SAC, PPO and PlaNet on the same tasks, several seeds each.

    python -m benchmarks.compare --quick                       # tiny grid, minutes: format example, not results
    python -m benchmarks.compare --methods cem sac --targets diagonal --seeds 0 1 --jobs 2
    python -m benchmarks.compare --report                      # only (re)write docs/RESULTS.md from finished cells

The grid (methods x variants x targets x seeds, with budgets) is data: benchmarks/compare.yaml (``full`` and
``quick``). Each cell runs the project's own entry point (``python -m planners.X`` / ``python -m agents.X``) as a
subprocess into ``<out>/<method>/<variant>/<target>/seed<s>/`` and is finished when its ``results.json`` exists:
finished cells are skipped, a learner cell with a ``checkpoint.pt`` but no ``results.json`` continues with
``--resume``, so a long comparison can be split over sessions. ``--jobs N`` runs N cells at once (subprocesses);
``--ray ADDRESS`` (``local`` for ``ray.init()``) runs them as Ray tasks instead (optional dependency).

The report (docs/RESULTS.md, docs/figures/) only reads finished cells; its confidence intervals (stats.py, scipy):
a t-interval over seeds and a Wilson score interval over the pooled episodes.
Success at 1 cm: the episode terminated with shape_error < 0.01 m (the env's success). Success at 2 cm: the
episode's last shape_error < 2 cm; an episode ends at its first move under 1 cm or after max-steps moves, for
planners and learners alike, so this is "ended within 2 cm". Planners also get "moves to 2 cm" from their per-move
``errors`` (first move under 2 cm).

Modules: grid (the YAML, cells, command lines), runner (subprocesses, resume, Ray), stats (intervals, row
statistics), costs (planning against learning), report (the markdown), figures (matplotlib), cli (main).
"""
from .cli import main
from .costs import PAYBACK_SLACK, cost_section, payback, row_cost
from .figures import make_cost_figures, make_figures
from .grid import GRID_FILE, NAMED, ROOT, build_cells, cell_dir, command_line, is_done, load_grid
from .report import COLUMNS, harness_command, machine_label, task_groups, write_report
from .runner import machine_info, merge_subruns, random_target_names, run_cell, run_cells
from .stats import row_stats, t_interval, t_quantile, wilson

__all__ = ["COLUMNS", "GRID_FILE", "NAMED", "PAYBACK_SLACK", "ROOT", "build_cells", "cell_dir", "command_line",
           "cost_section", "harness_command", "is_done", "load_grid", "machine_info", "machine_label", "main",
           "make_cost_figures", "make_figures", "merge_subruns", "payback", "random_target_names", "row_cost",
           "row_stats", "run_cell", "run_cells", "t_interval", "t_quantile", "task_groups", "wilson",
           "write_report"]
