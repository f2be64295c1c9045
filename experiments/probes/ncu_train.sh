#!/usr/bin/env bash
# Nsight Compute on the training step (issue 20, item 4): for each "ROBOT HIDDEN BATCH"
# configuration, train_step_floor.py times the step against its FLOP and memory floors (no
# profiler), then ncu records every kernel of two single steps (bracketed by cudaProfilerStart/Stop)
# with its duration and its compute and memory throughput; ncu_summary.py sums them per step.
# Usage (repository root, on a GPU machine whose runtime lets ncu read the counters):
#   bash experiments/probes/ncu_train.sh OUT ["go1 256 1024;g1 256 1024;..."]
# Sessions 20-70's runs crashed (SIGSEGV) under kernel and application replay alike, with the
# settings below and XLA's plain allocator: it was ncu itself, following the child processes XLA
# starts while compiling (session 71, results/throughput/README.md); --target-processes
# application-only below keeps it on the Python process. Settable: NCU_REPLAY=application (the
# whole process rerun once per metric pass) and NCU_ALLOCATOR=platform (XLA's plain cudaMalloc).
set -uo pipefail
# ncu replays kernels in the process: XLA must not take the GPU's memory up front, and the
# profiled steps launch their kernels one by one (no CUDA graphs), else the process segfaults
export XLA_PYTHON_CLIENT_PREALLOCATE=false
[ -z "${NCU_ALLOCATOR:-}" ] || export XLA_PYTHON_CLIENT_ALLOCATOR=$NCU_ALLOCATOR
replay=${NCU_REPLAY:-kernel}
out=$1
configs=${2:-"go1 256 1024;go1 256 8192;g1 256 1024"}
IFS=';' read -ra list <<< "$configs"
for c in "${list[@]}"; do
  read -r robot hidden batch <<< "$c"
  name=ncu_train_${robot}_${hidden}_b${batch}
  echo "== $c" | tee -a "$out/ncu_train.log"
  python3 experiments/probes/train_step_floor.py --robot "$robot" --hidden "$hidden" \
    --batch "$batch" --out "$out" 2>&1 | grep -v -i "warn" | tail -2 | tee -a "$out/ncu_train.log"
  XLA_FLAGS="${XLA_FLAGS:-} --xla_gpu_enable_command_buffer=" timeout 300 ncu --target-processes application-only --clock-control none --profile-from-start off --replay-mode "$replay" \
    --metrics gpu__time_duration.sum,sm__throughput.avg.pct_of_peak_sustained_elapsed,gpu__compute_memory_throughput.avg.pct_of_peak_sustained_elapsed,launch__grid_size \
    --csv --page raw --log-file "$out/$name.csv" \
    python3 experiments/probes/train_step_floor.py --robot "$robot" --hidden "$hidden" \
    --batch "$batch" --chunk 2 --repeats 1 --cuda-profile --profile-steps 2 \
    >> "$out/ncu_train.err" 2>&1 || echo "ncu failed ($?), see ncu_train.err" | tee -a "$out/ncu_train.log"
  python3 experiments/probes/ncu_summary.py "$out/$name.csv" --steps 2 | tee -a "$out/ncu_train.log"
done
