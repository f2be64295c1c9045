#!/usr/bin/env bash
# Closed loop through every trained seed of STRIDE, DeLaN + MLP and ONN in one Table I runs folder
# (issue 19: the planners' spread over trained models, not only over planner draws).
#   bash experiments/closed_loop_seeds.sh ROBOT RUNS OUT LIMIT_S SCENARIOS [closed-loop flags...]
# RUNS holds <model>-s<seed> run folders (experiments/table1.py's runs folder, e.g. on the GPU
# machine after `DATA=walk TW=1 TF=0.25 bash experiments/table1_device.sh ...`:
# /tmp/table1/runs/g1_walk_tw1_tf0.25-paper). Seed 0 is named MODEL, seed S MODEL_sS (as
# experiments/trained_seeds.py reads them); the runs go kind by kind, so the seeds of one kind
# share one compiled episode. The rows and the rest: experiments/closed_loop_targets.sh (OUT.tgz at
# the end; resumable in OUT). DRY=1 prints the command instead.
set -u
robot=$1 runs=$2 out=$3 limit=$4 scen=$5
shift 5
models=""
for kind in stride delan onn; do
  for d in "$runs/$kind"-s*; do
    [ -f "$d/model.json" ] || continue
    seed=${d##*-s}
    name=$kind; [ "$seed" = 0 ] || name=${kind}_s$seed
    models+="$name=$d,"
  done
done
[ -n "$models" ] || { echo "no stride/delan/onn-s<seed> runs with a model.json in $runs" >&2; exit 2; }
cmd=(bash experiments/closed_loop_targets.sh "$robot" "$out" "$limit" "${models%,}" "$scen" "$@")
if [ "${DRY:-0}" = 1 ]; then printf '%q ' "${cmd[@]}"; echo; else "${cmd[@]}"; fi
