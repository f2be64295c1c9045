#!/usr/bin/env bash
# MPPI step latency on one GPU under different compilations of the same planner: the horizon as a
# loop or unrolled, and XLA's command buffers (CUDA graphs) on, off or widened. Go1 STRIDE (NFE 2),
# K=1024, H=30, at the control rate; each variant in its own process (XLA reads its flags once).
# Usage (repository root, on the GPU machine): bash experiments/probes/mppi_gpu_speed.sh OUT [MODELS]
set -uo pipefail
out=${1:-runs/mppi_gpu_speed}
models=${2:-stride}
mkdir -p "$out"
bench() {  # tag unroll xla_flags
  echo "== $1 (unroll $2, XLA_FLAGS '$3')"
  XLA_FLAGS="$3" python3 -m stride_jax.cli bench-mppi --robots go1 --models "$models" \
    --samples 1024 --horizons 30 --substeps 1 --unroll "$2" --repeats 20 --out "$out/$1" 2>&1 |
    grep -E "K=|Error|error|Check failed" | tail -4
}
bench loop 1 ""
bench unrolled 0 ""
bench unrolled_no_graphs 0 "--xla_gpu_enable_command_buffer="
bench loop_graph_loops 1 "--xla_gpu_enable_command_buffer=FUSION,CUBLAS,CUBLASLT,CUSTOM_CALL,WHILE,CONDITIONAL"
bench unrolled_small_graphs 0 "--xla_gpu_graph_min_graph_size=1"
bench unrolled_graph_all 0 "--xla_gpu_enable_command_buffer=FUSION,CUBLAS,CUBLASLT,CUSTOM_CALL,CUDNN,WHILE,CONDITIONAL --xla_gpu_graph_min_graph_size=1"
echo "== ENTRY operations of the unrolled step (default flags)"
python3 experiments/probes/mppi_hlo_ops.py --robot go1 --model stride 2>&1 | grep -v -i "warn\|import" | head -25
