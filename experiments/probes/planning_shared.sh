#!/usr/bin/env bash
# What one network for L and V (LNNConfig.shared) and one flow evaluation (NFE 1) cost a
# planning-sized STRIDE in accuracy (issue 4: 50 Hz on a 2-core CPU at K=128, H=16). Trains Go1
# STRIDE 64 x 3 and 128 x 3 with the shared network on the Table I data with Table I's settings
# (as experiments/probes/planning_sizes.sh, whose two-network 64 x 3 run is evaluated again at NFE 1),
# then evaluates each at NFE 2 and 1 with Table I's evaluation preset. Resumable: finished
# steps are skipped. Usage (repository root, one GPU): bash experiments/probes/planning_shared.sh [OUT]
set -euo pipefail
out=${1:-runs/planning_shared}
steps=12000
export XLA_PYTHON_CLIENT_PREALLOCATE=false
data=data/go1-paper
mkdir -p logs "$out"
if [ ! -f "$data/meta.json" ]; then
  python3 -m stride_jax.cli data --robot go1 --preset paper --episodes 1024 --out "$data" \
    >logs/data-go1.log 2>&1
fi
for h in 64 128; do
  run=$out/stride-h$h-shared
  if ! grep -q '"finished": true' "$run/summary.json" 2>/dev/null; then
    python3 -m stride_jax.cli train --robot go1 --model stride --preset paper --steps "$steps" \
      --hidden "$h" --depth 3 --seed 0 --shared-lnn --data "$data" --out "$run" \
      >"$out/train-h$h-shared.log" 2>&1 &
  fi
done
if [ ! -d "$out/stride-h64" ]; then cp -r results/mppi_latency/planning_sizes/stride-h64 "$out/"; fi
wait
for spec in stride-h64-shared:2 stride-h64-shared:1 stride-h128-shared:2 stride-h128-shared:1 \
            stride-h64:1; do
  run=${spec%:*} nfe=${spec#*:}
  [ -f "$out/eval-$run-nfe$nfe/table.md" ] && continue
  python3 -m stride_jax.cli eval --preset default --runs "$out/$run" --nfe "$nfe" \
    --out "$out/eval-$run-nfe$nfe" --label "bash experiments/probes/planning_shared.sh $out" \
    >"$out/eval-$run-nfe$nfe.log" 2>&1 &
done
wait
for f in "$out"/eval-*/table.md; do echo "$f: $(grep '^| stride' "$f")"; done
