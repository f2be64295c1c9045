#!/usr/bin/env bash
# How much accuracy a planning-sized STRIDE gives up (issue 4: 50 Hz replanning on a 2-core CPU at
# K=128, H=16 is below the FLOP floor of the paper's 256 x 3 networks). Trains Go1 STRIDE with
# 128 x 3 and 64 x 3 networks on the Table I data with Table I's settings (seed 0, 12000 steps,
# the paper training preset) and evaluates them beside the committed 256 x 3 STRIDE and DeLaN
# (results/models/go1/*-s0) on the same regenerated data, with Table I's evaluation preset.
# Usage (repository root, one GPU): bash experiments/probes/planning_sizes.sh [OUT] [STEPS]
set -euo pipefail
out=${1:-runs/planning_sizes}
steps=${2:-12000}
export XLA_PYTHON_CLIENT_PREALLOCATE=false
data=data/go1-paper
mkdir -p logs
if [ ! -f "$data/meta.json" ]; then
  python3 -m stride_jax.cli data --robot go1 --preset paper --episodes 1024 --out "$data" \
    >logs/data-go1.log 2>&1
fi
rm -rf "$out" && mkdir -p "$out"
for h in 128 64; do
  python3 -m stride_jax.cli train --robot go1 --model stride --preset paper --steps "$steps" \
    --hidden "$h" --depth 3 --seed 0 --data "$data" --out "$out/stride-h$h" \
    >"$out/train-h$h.log" 2>&1 &
done
for m in stride delan; do  # the committed 256 x 3 runs: their files and best checkpoint alone
  src=results/models/go1/$m-s0 run=$out/$m-h256
  step=$(python3 -c 'import json,sys; print(json.load(open(sys.argv[1]))["best_step"])' "$src/summary.json")
  mkdir -p "$run/best" && cp "$src"/*.json "$run/" && cp -r "$src/best/$step" "$run/best/"
done
wait
tail -n 2 "$out"/train-h*.log
# one evaluation per run (the table merges runs of one model name as seeds), side by side
for run in stride-h256 stride-h128 stride-h64 delan-h256; do
  python3 -m stride_jax.cli eval --preset default --runs "$out/$run" --out "$out/eval-$run" \
    --label "bash experiments/probes/planning_sizes.sh $out $steps" >"$out/eval-$run.log" 2>&1 &
done
wait
grep -h "^| stride\|^| delan" "$out"/eval-*/table.md
