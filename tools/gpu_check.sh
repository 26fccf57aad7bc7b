#!/usr/bin/env bash
# The prepared GPU check (issue: training throughput, GPU): in under 8 minutes on one
# GPU, run the CUDA tests, benchmarks/train.py on CUDA (env steps/s) and the large-team
# simulator benchmark (agent-steps/s at M = 10 to 10,000).
#
#   tools/gpu_check.sh              # run it (needs the project installed with a CUDA torch)
#   tools/gpu_check.sh --dry-run    # print the commands only
#   tools/gpu_check.sh --agents "3 10" --updates 3 --num-envs 4096 --precisions "fp32 bf16"
#   tools/gpu_check.sh --python python3 --train-seconds 170 --run-dir /tmp/gpu-cov3
#
# --python: the interpreter that has torch, taichi and this project (default: python).
# --train-seconds S: afterwards, train coverage M = 3 with the `gpu` preset on CUDA for at
# most S seconds (Ctrl-C at the limit: the checkpoint is kept; `swarm eval` it anywhere) into
# --run-dir (default: runs/gpu-coverage-m3-DATE-TIME).
# Every step runs even when an earlier one failed; the exit status says whether all passed.
# Target on one H100: >= 100k env steps/s at M = 3 (docs/BENCHMARKS.md, GPU).
set -uo pipefail

usage() { sed -n '2,16p' "$0" | sed 's/^# \{0,1\}//'; }
dry_run=0
agents="3 10"
updates=3
num_envs=4096
precisions="fp32 bf16"
python=python
train_seconds=0
run_dir=runs/gpu-coverage-m3-$(date +%Y%m%d-%H%M%S)
while [ $# -gt 0 ]; do
    case "$1" in
        --dry-run) dry_run=1 ;;
        --agents) agents="${2:?--agents needs a value}"; shift ;;
        --updates) updates="${2:?--updates needs a value}"; shift ;;
        --num-envs) num_envs="${2:?--num-envs needs a value}"; shift ;;
        --precisions) precisions="${2:?--precisions needs a value}"; shift ;;
        --python) python="${2:?--python needs a value}"; shift ;;
        --train-seconds) train_seconds="${2:?--train-seconds needs a value}"; shift ;;
        --run-dir) run_dir="${2:?--run-dir needs a value}"; shift ;;
        -h|--help) usage; exit 0 ;;
        *) echo "gpu_check.sh: unknown option '$1'" >&2; usage >&2; exit 2 ;;
    esac
    shift
done
for n in $agents $updates $num_envs; do
    case "$n" in ''|*[!0-9]*|0) echo "gpu_check.sh: expected positive integers, got '$n'" >&2; exit 2 ;; esac
done
case "$train_seconds" in ''|*[!0-9]*) echo "gpu_check.sh: --train-seconds expects seconds (0 = no training), got '$train_seconds'" >&2; exit 2 ;; esac
[ -z "${precisions// /}" ] && { echo "gpu_check.sh: --precisions needs fp32 and/or bf16" >&2; exit 2; }
for p in $precisions; do
    case "$p" in fp32|bf16) ;; *) echo "gpu_check.sh: --precisions takes fp32 and/or bf16, got '$p'" >&2; exit 2 ;; esac
done

run_dir=$(realpath -m "$run_dir")  # relative to where the script was called from
cd "$(dirname "$0")/.."
failed=()
run() {
    echo "+ $*"
    if [ "$dry_run" = 0 ]; then
        local t0=$SECONDS
        "$@" || failed+=("$*")
        echo "  ($((SECONDS - t0)) s)"
    fi
}
run nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
run env TAICHI_SWARM_TEST_ARCH=cuda "$python" -m pytest -q -p no:cacheprovider -o addopts= tests/test_taichi_swarm/test_cuda.py
for m in $agents; do
    # shellcheck disable=SC2086  # precisions is a list
    run "$python" benchmarks/train.py --device cuda --arch cuda --presets gpu --threads 1 --agents "$m" \
        --updates "$updates" --num-envs "$num_envs" --no-compile --precisions $precisions
done
# large teams on CUDA: simulator cost per agent-step at M = 10 / 100 / 1000 (10,000 agents per
# step) with neighbour lists, one thread per environment against every agent in parallel (the
# "wide" rows, CUDA's default), and one environment of M = 10,000 (docs/SWARM.md). Not the
# exact assignment: one GPU thread solving a team's M x M problem took 5.5 s a step at M = 1000
# on an H200
run "$python" benchmarks/swarm.py --arch cuda --seconds 1 --skip-dense-large --layouts dense "lists K=16 free" \
    "lists K=16 free wide" "lists KL=16 free" "lists KL=16 free wide"
if [ "$train_seconds" -gt 0 ]; then
    # SIGINT at the limit: the trainer saves its checkpoint and exits 130 (not a failure
    # here); a process still there 60 s later is killed
    train=(timeout --preserve-status -k 60 -s INT "$train_seconds" "$python" -m swarm_cli train --task coverage
        --agents 3 --preset gpu --device cuda --arch cuda --no-compile --updates 1000 --eval-every 10
        --eval-episodes 500 --transfer-offsets --no-progress --run-dir "$run_dir")
    echo "+ ${train[*]}"
    if [ "$dry_run" = 0 ]; then
        "${train[@]}"
        rc=$?
        case $rc in 0|130) ;; *) failed+=("training (exit $rc)") ;; esac
        echo "  checkpoint: $run_dir (evaluate: swarm eval $run_dir/policy.pt --episodes 500 --seed 777)"
    fi
fi
[ "$dry_run" = 1 ] && exit 0
if [ "${#failed[@]}" -gt 0 ]; then
    printf 'gpu_check.sh: FAILED: %s\n' "${failed[@]}" >&2
    exit 1
fi
echo "gpu_check.sh: all steps passed"
