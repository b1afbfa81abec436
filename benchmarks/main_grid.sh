#!/bin/bash
# The comparison's grid (benchmarks/compare.yaml): the main rows, cheapest first, two cells at once, niced; then the
# appendix and the secondary rows. Finished cells are skipped (also those only recorded in docs/results/cells.jsonl,
# when the run folders stayed on another machine: --skip-recorded) and learners resume, so rerun it to continue:
#   nohup setsid benchmarks/main_grid.sh > runs/main_grid.log 2>&1 &
# then `python -m benchmarks.compare --collect --out runs/compare` adds the finished cells to docs/results/cells.jsonl
# and rebuilds docs/RESULTS.md and the README's summary.
cd "$(dirname "$0")/.." || exit 1
PY=${PYTHON:-.venv/bin/python}
C="$PY -m benchmarks.compare --out runs/compare --jobs ${JOBS:-2} --no-report --no-progress --skip-recorded"
MAIN="random random_curve arc s_curve hook wave"
nice -n 10 $C --methods greedy cem gradient --variants default --targets $MAIN
nice -n 10 $C --methods apg ppo --variants tuned
nice -n 10 $C --methods ppo --variants fewest_moves
# the precision rows (issue 50: the task at 5 mm mean and 2 cm at the worst node; the planners run until 2 mm), one
# pool, cheapest first
nice -n 10 $C --rows cem/precise gradient/precise pets/precise ppo/precise latent/precise cem/precise_image
# the routing rows (issue 59: the planners on routes among pegs, without and with the second gripper, and with the
# stall escape)
nice -n 10 $C --rows greedy/route greedy/route_pin cem/route cem/route_pin cem/route_escape cem/route_pin_escape \
  gradient/route gradient/route_pin gradient/route_escape gradient/route_pin_escape
# the learners' routing rows (issue 60: trained on random boards, read on the held-out layouts too), CEM at the world
# models' planning budget (their planner with a perfect model), then the routing rows from 64 px pictures (CEM and
# the two world models, obs "perceived")
nice -n 10 $C --rows apg/route pets/route pets/route_pin ppo/route ppo/route_pin ppo/route_rollouts latent/route \
  latent/route_pin sac/route cem/route_wm_budget cem/route_image pets/route_image latent/route_image
# every other row in one pool, so both jobs stay busy to the last cell: the main rows first, cheapest first, then
# the named lines (planners), the distillation (its teacher: the same seed's ppo/fewest_moves cell), the APG
# variants and the secondary rows
nice -n 10 $C --rows cem/tuned_image ppo/tuned_image pets/tuned_image latent/tuned_image pets/tuned latent/tuned sac/tuned planet/default \
    sac/tuned_image planet/image greedy/default cem/default gradient/default distill/default \
    apg/greedy apg/h4 apg/h4_critic apg/score sac/points ppo/points sac/abs_diff sac/delta_gain \
    sac/points_utd1 pets/upt100 pets/h2 sac/image ppo/image ppo/image_e2e
