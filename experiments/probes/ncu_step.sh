#!/usr/bin/env bash
# Nsight Compute on the whole-step kernel (stride_fused_step) of the MPPI model step: for each
# "ROBOT HIDDEN KERNEL" configuration, two launches of the kernel (K = SAMPLES rows) profiled with
# the sections that place it against the device's compute and memory ceilings (speed of light,
# compute and memory workload, occupancy, launch statistics, warp stalls). One CSV per
# configuration in OUT (ncu's own log lines among its rows), the probe's output in ncu_step.err.
# Usage (repository root, on a GPU machine whose runtime lets ncu read the counters; the clocks
# are left alone):
#   bash experiments/probes/ncu_step.sh OUT [SAMPLES] ["go1 256 pallas-step;g1 64 pallas-step-bf16;..."]
set -uo pipefail
out=$1; samples=${2:-1024}
configs=${3:-"go1 64 pallas-step-bf16;go1 256 pallas-step;go1 256 pallas-step-bf16;g1 64 pallas-step-bf16"}
IFS=';' read -ra list <<< "$configs"
for c in "${list[@]}"; do
  read -r robot hidden kernel <<< "$c"
  name=ncu_${robot}_${hidden}_${kernel}
  echo "== $c" | tee -a "$out/ncu_step.log"
  # the probe's own timing first (no profiler), then the profiled launches
  python3 experiments/probes/fused_step_check.py --robot "$robot" --hidden "$hidden" \
    --samples "$samples" --kernels "$kernel" --horizon 30 --repeats 10 2>&1 \
    | grep -v -i "warn\|warp" | tee -a "$out/ncu_step.log"
  # application-only: ncu following the compiler processes XLA starts crashes it (session 71)
  timeout 240 ncu --target-processes application-only --clock-control none -k regex:stride_fused_step -c 2 \
    --section SpeedOfLight --section ComputeWorkloadAnalysis --section MemoryWorkloadAnalysis \
    --section Occupancy --section LaunchStats --section WarpStateStats --csv --page details \
    --log-file "$out/$name.csv" \
    python3 experiments/probes/fused_step_check.py --robot "$robot" --hidden "$hidden" \
    --samples "$samples" --kernels "$kernel" --horizon 1 --repeats 1 >> "$out/ncu_step.err" 2>&1 \
    || echo "ncu failed ($?), see ncu_step.err" | tee -a "$out/ncu_step.log"
done
