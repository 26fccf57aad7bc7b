#!/usr/bin/env bash
# The prepared GPU check (issue: training throughput, GPU): in under 8 minutes on one
# GPU, run the CUDA tests and `swarm bench train` on CUDA, and print env steps/s.
#
#   tools/gpu_check.sh              # run it (needs the project installed with a CUDA torch)
#   tools/gpu_check.sh --dry-run    # print the commands only
#   tools/gpu_check.sh --agents "3 10" --updates 3 --num-envs 4096
#
# Target on one H100: >= 100k env steps/s at M = 3 (docs/BENCHMARKS.md, GPU).
set -euo pipefail

usage() { sed -n '2,9p' "$0" | sed 's/^# \{0,1\}//'; }
dry_run=0
agents="3 10"
updates=3
num_envs=4096
while [ $# -gt 0 ]; do
    case "$1" in
        --dry-run) dry_run=1 ;;
        --agents) agents="${2:?--agents needs a value}"; shift ;;
        --updates) updates="${2:?--updates needs a value}"; shift ;;
        --num-envs) num_envs="${2:?--num-envs needs a value}"; shift ;;
        -h|--help) usage; exit 0 ;;
        *) echo "gpu_check.sh: unknown option '$1'" >&2; usage >&2; exit 2 ;;
    esac
    shift
done
for n in $agents $updates $num_envs; do
    case "$n" in ''|*[!0-9]*|0) echo "gpu_check.sh: expected positive integers, got '$n'" >&2; exit 2 ;; esac
done

cd "$(dirname "$0")/.."
run() {
    echo "+ $*"
    if [ "$dry_run" = 0 ]; then "$@"; fi
}
run nvidia-smi --query-gpu=name,memory.total --format=csv,noheader
run env TAICHI_SWARM_TEST_ARCH=cuda python -m pytest -q -p no:cacheprovider tests/test_taichi_swarm/test_cuda.py
for m in $agents; do
    run swarm bench train --device cuda --arch cuda --presets gpu --threads 1 --agents "$m" \
        --updates "$updates" --num-envs "$num_envs"
done
