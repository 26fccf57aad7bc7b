#!/usr/bin/env bash
# The large-team policies on the agents' own auction by messages (landmark_order radio), from
# scratch in two cells: M = 10 trained from a fresh network, then M = 100 trained on from it.
# Each agent senses landmarks within the task's sense radius and keeps a table of the KL
# nearest; its landmark comes from 8 message rounds a step with the teammates it hears (comm
# radius 1, its 12 nearest). The M = 100 policy is evaluated on 100 fresh episodes at seeds 777
# and 4242 (coverage also at M = 1000); tools/make_zoo.py reads results/radio/TASK-rc-m100-radio.
#
#   tools/radio_recipe.sh coverage|line|formation     # 30-50 minutes each on one CPU core; coverage's M = 1000
#                                                     # evaluation about 30 more
set -euo pipefail
task=${1:?usage: tools/radio_recipe.sh coverage|line|formation}
# what each agent senses at M = 10 and at M = 100: the KL nearest landmarks within the sense
# radius, also its auction table's size (at M = 10 line's 24 hold every target; at M = 100 a table
# of 24 leaves line at 92%, one of 48 at 100%, docs/SWARM.md)
case $task in
  coverage) small="--landmark-neighbours 64 --sense-radius 6.0"; lists=$small ;;
  line) small="--landmark-neighbours 24 --sense-radius 3.0"; lists="--landmark-neighbours 48 --sense-radius 3.0" ;;
  formation) small="--landmark-neighbours 24 --sense-radius 1.5"; lists=$small ;;
  *) echo "tools/radio_recipe.sh: the task must be coverage, line or formation, got $task" >&2; exit 2 ;;
esac
setting="--task $task --comm rc --neighbours 12 --landmark-occupancy --landmark-order radio --auction-rounds 8
  --scale density --assignment free --reward agent --action-space fine
  --model.self-position none --model.edge-position relative --transfer-offsets --torch-threads 1 --no-progress"
small_run=results/radio/$task-rc-m10-radio
run=results/radio/$task-rc-m100-radio
# shellcheck disable=SC2086  # $setting and $lists are lists of options
swarm train $setting $small --agents 10 --eval-every 50 --eval-episodes 100 --updates 100 --run-dir "$small_run"
# shellcheck disable=SC2086
swarm train $setting $lists --agents 100 --ppo.lr 1e-4 --ppo.lr-end 3e-5 --ppo.num-envs 12 --ppo.entropy-coef 0.003 \
  --eval-every 25 --eval-episodes 50 --updates 25 --init-from "$small_run/policy.pt" --run-dir "$run"
for seed in 777 4242; do
  swarm eval "$run/policy.pt" --episodes 100 --seed $seed --json "$run/eval-$seed.json"
done
if [ "$task" = coverage ]; then
  swarm eval "$run/policy.pt" --agents 1000 --episodes 100 --seed 777 --json "$run/eval-m1000-777.json"
fi
