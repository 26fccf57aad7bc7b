#!/usr/bin/env bash
# The training that is slow on two CPU cores, prepared for a GPU lent for a few minutes:
# Table 2's coverage curricula without and with EMP (UC and RC, all from scratch) and
# formation's curricula with the landmark offset concatenated (the authors' network), the
# first 6 jobs of --list by default; Table 1's M = 6 cells and the other curricula on request.
# Each a
# `swarm` command with the `gpu` preset on CUDA, several at a time on the one GPU.
#
#   tools/gpu_campaign.sh --list                      # the jobs and their commands
#   tools/gpu_campaign.sh --dry-run                   # print what would run
#   tools/gpu_campaign.sh --python python3 --seconds 240 --parallel 4 --out "$OUT" [JOB ...]
#   tools/gpu_campaign.sh --device cpu --seconds 20 table1-cov3-rc   # a smoke test without a GPU
#   tools/gpu_campaign.sh --python python3 --work /tmp/campaign --seconds 400 --out "$OUT"
#       (the same --work again, on a machine still warm, resumes each job where it stopped)
#
# Each job stops at its own end or after --seconds (Ctrl-C: the trainer keeps its
# checkpoint; killed 60 s later if still there). Then each run directory, without
# checkpoint.pt (weights-only policy.pt, config, metrics; curves only for a run that
# finished) and with the job's log, is packed into OUT/JOB.tgz: at most 8 jobs per call,
# one file each. Evaluate what comes back anywhere, e.g.
#   swarm eval RUN/policy.pt --episodes 500 --seed 777
set -uo pipefail

usage() { sed -n '2,/^set -uo/p' "$0" | sed '$d' | sed 's/^# \{0,1\}//'; }
common="--preset gpu --no-compile --no-progress --eval-every 10 --eval-episodes 500"
curr="--max-updates-per-stage 200 --fresh-eval-episodes 500 --fresh-eval-seed 777 --transfer-offsets"
declare -A JOBS=(
    [table1-cov6-uc]="train --task coverage --agents 6 --comm uc --updates 400 --transfer-offsets -1 1"
    [table1-cov6-rc]="train --task coverage --agents 6 --comm rc --updates 400 --transfer-offsets -1 1"
    [table1-line6-rc]="train --task line --agents 6 --comm rc --updates 400 --transfer-offsets -1 1"
    [table1-cov3-rc]="train --task coverage --agents 3 --comm rc --updates 400 --transfer-offsets 1 2"
    [curr-cov-rc]="curriculum --task coverage --comm rc $curr"
    [curr-form-rc]="curriculum --task formation --comm rc $curr"
    [curr-line-rc]="curriculum --task line --comm rc $curr"
    [curr-form-uc]="curriculum --task formation --comm uc $curr"
    [curr-cov-uc]="curriculum --task coverage --comm uc $curr"
    [curr-form-uc-concat]="curriculum --task formation --comm uc --model.entity-mode concat $curr"
    [curr-form-rc-concat]="curriculum --task formation --comm rc --model.entity-mode concat $curr"
    [curr-cov-uc-noemp]="curriculum --task coverage --comm uc --model.entity-mode padded $curr"
    [curr-cov-rc-noemp]="curriculum --task coverage --comm rc --model.entity-mode padded $curr"
)
ORDER="curr-cov-uc-noemp curr-cov-rc-noemp curr-cov-uc curr-cov-rc curr-form-uc-concat curr-form-rc-concat table1-cov6-uc curr-line-rc curr-form-rc table1-cov6-rc table1-line6-rc curr-form-uc table1-cov3-rc"
DEFAULT="curr-cov-uc-noemp curr-cov-rc-noemp curr-cov-uc curr-cov-rc curr-form-uc-concat curr-form-rc-concat"

dry_run=0
device=cuda
python=python
seconds=240
parallel=4
out=runs/gpu-campaign
work=
jobs=()
while [ $# -gt 0 ]; do
    case "$1" in
        --dry-run) dry_run=1 ;;
        --list) for j in $ORDER; do echo "$j: swarm ${JOBS[$j]} $common --device cuda --arch cuda"; done; exit 0 ;;
        --device) device="${2:?--device needs a value}"; shift ;;
        --python) python="${2:?--python needs a value}"; shift ;;
        --seconds) seconds="${2:?--seconds needs a value}"; shift ;;
        --parallel) parallel="${2:?--parallel needs a value}"; shift ;;
        --out) out="${2:?--out needs a value}"; shift ;;
        --work) work="${2:?--work needs a value}"; shift ;;
        -h|--help) usage; exit 0 ;;
        -*) echo "gpu_campaign.sh: unknown option '$1'" >&2; usage >&2; exit 2 ;;
        *)
            if [ -z "${JOBS[$1]+x}" ]; then
                echo "gpu_campaign.sh: unknown job '$1' (jobs: $ORDER)" >&2
                exit 2
            fi
            for k in "${jobs[@]}"; do
                [ "$k" = "$1" ] && { echo "gpu_campaign.sh: job '$1' named twice (one run directory each)" >&2; exit 2; }
            done
            jobs+=("$1") ;;
    esac
    shift
done
case "$device" in cuda|cpu) ;; *) echo "gpu_campaign.sh: --device takes cuda or cpu, got '$device'" >&2; exit 2 ;; esac
for n in "$seconds" "$parallel"; do
    case "$n" in ''|*[!0-9]*|0) echo "gpu_campaign.sh: --seconds and --parallel take positive integers, got '$n'" >&2; exit 2 ;; esac
done
[ ${#jobs[@]} -eq 0 ] && read -r -a jobs <<< "$DEFAULT"
if [ ${#jobs[@]} -gt 8 ]; then
    echo "gpu_campaign.sh: at most 8 jobs per call (one packed file each), got ${#jobs[@]}" >&2
    exit 2
fi

out=$(realpath -m "$out")  # relative to where the script was called from
[ -n "$work" ] && work=$(realpath -m "$work")
cd "$(dirname "$0")/.."
resume_hint=$dry_run  # a dry run without --work names no directory that will exist
if [ -n "$work" ]; then
    resume_hint=0
    [ "$dry_run" = 0 ] && mkdir -p "$work" "$out"
elif [ "$dry_run" = 1 ]; then
    work=/tmp/gpu-campaign.DRY-RUN
else
    work=$(mktemp -d /tmp/gpu-campaign.XXXXXX) && mkdir -p "$out"
fi
[ "$resume_hint" = 0 ] && printf 'run directories under %s (--work %q again resumes them)\n' "$work" "$work"
run_job() {  # JOB: its command under the time limit, then its run directory packed
    local j=$1 dir="$work/$1"
    set -- timeout --preserve-status -k 60 -s INT "$seconds" "$python" -m swarm_cli
    if [[ ${JOBS[$j]} == train\ * && -e "$dir/checkpoint.pt" ]]; then  # a train run continues by --resume
        set -- "$@" train --resume "$dir" --no-progress --device "$device" --arch "$device"
    else  # (a curriculum resumes by the same command)
        # shellcheck disable=SC2086  # the job's arguments are a word list
        set -- "$@" ${JOBS[$j]} $common --device "$device" --arch "$device" --run-dir "$dir"
    fi
    echo "+ $*"
    [ "$dry_run" = 1 ] && return 0
    "$@" >> "$work/$j.log" 2>&1  # appended: a resumed job's log holds every call
    local rc=$?
    case $rc in 0) echo "$j: finished" ;; 130) echo "$j: stopped at the $seconds s limit" ;; *) echo "$j: FAILED (exit $rc)" ;; esac
    local pack=("$j.log")
    [ -d "$dir" ] && pack+=("$j")
    tar czf "$out/$j.tgz" --exclude=checkpoint.pt -C "$work" "${pack[@]}"
}
running=0
for j in "${jobs[@]}"; do
    if [ "$dry_run" = 1 ]; then run_job "$j"; continue; fi
    run_job "$j" &
    running=$((running + 1))
    if [ "$running" -ge "$parallel" ]; then wait -n; running=$((running - 1)); fi
done
wait
[ "$dry_run" = 0 ] && ls -la "$out"
exit 0
