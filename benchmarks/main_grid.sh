#!/bin/bash
# The comparison's main grid (benchmarks/compare.yaml `main`), cheapest rows first, two cells at once, niced; then the
# appendix and the secondary rows. Finished cells are skipped and learners resume, so rerun it to continue:
#   nohup setsid benchmarks/main_grid.sh > runs/main_grid.log 2>&1 &
# then `python -m benchmarks.compare --collect --out runs/compare` adds the finished cells to docs/results/cells.jsonl
# and rebuilds docs/RESULTS.md and the README's summary.
cd "$(dirname "$0")/.." || exit 1
PY=${PYTHON:-.venv/bin/python}
C="$PY -m benchmarks.compare --out runs/compare --jobs ${JOBS:-2} --no-report --no-progress"
MAIN="random random_curve arc s_curve hook wave"
nice -n 10 $C --methods greedy cem gradient --variants default --targets $MAIN
nice -n 10 $C --methods apg ppo --variants tuned
nice -n 10 $C --methods ppo --variants fewest_moves
nice -n 10 $C --methods cem ppo pets --variants tuned_image
nice -n 10 $C --methods pets --variants tuned
nice -n 10 $C --methods sac --variants tuned
nice -n 10 $C --methods planet --variants default
nice -n 10 $C --methods sac --variants tuned_image
nice -n 10 $C --methods planet --variants image
nice -n 10 $C --methods greedy cem gradient --variants default --targets horizontal vertical diagonal antidiagonal
nice -n 10 $C --methods apg --variants greedy h4 h4_critic score
nice -n 10 $C --methods sac ppo --variants points abs_diff delta_gain
nice -n 10 $C --methods distill                  # its teacher: the same seed's ppo/fewest_moves cell
