#!/usr/bin/env bash
# The large-team policies on the agents' own auction by messages (landmark_order radio): each
# zoo entry NAME-rc-m100-radio is its shared-price auction entry trained 25 more updates (coverage 100) with
# the landmark each agent holds coming from the radio auction (8 message rounds a step), then
# evaluated on 100 fresh episodes at seed 777 (tools/make_zoo.py reads the run directory).
#
#   tools/radio_recipe.sh coverage|line|formation     # 9-15 minutes each on one CPU core
set -euo pipefail
task=${1:?usage: tools/radio_recipe.sh coverage|line|formation}
updates=25
case $task in
  coverage) lists="--landmark-neighbours 16 --sense-radius 6.0"; updates=100 ;;
  line) lists="--landmark-neighbours 24 --sense-radius 3.0" ;;
  formation) lists="--landmark-neighbours 24 --sense-radius 1.5" ;;
  *) echo "tools/radio_recipe.sh: the task must be coverage, line or formation, got $task" >&2; exit 2 ;;
esac
run=results/radio/$task-rc-m100-radio
swarm train --task "$task" --agents 100 --comm rc --neighbours 12 $lists --landmark-occupancy \
  --landmark-order radio --auction-rounds 8 --scale density --assignment free --reward agent --action-space fine \
  --model.self-position none --model.edge-position relative \
  --ppo.lr 1e-4 --ppo.lr-end 3e-5 --ppo.num-envs 12 --ppo.entropy-coef 0.003 \
  --eval-every 25 --eval-episodes 50 --updates $updates --transfer-offsets --torch-threads 1 --no-progress \
  --init-from "$task-rc-m100-auction" --run-dir "$run"
swarm eval "$run/policy.pt" --episodes 100 --seed 777 --json "$run/eval-777.json"
