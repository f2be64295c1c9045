#!/usr/bin/env bash
# The planner with fused kernels (stride_jax/dynamics/fused.py, fused_step.py) against XLA on one
# GPU: Go1 STRIDE (NFE 2, one network for L and V), K=1024, H=30, at the control rate, for each
# network size and kernel choice in its own run. Usage (repository root, on the GPU machine):
#   [KERNELS="xla pallas-step pallas-step-bf16"] bash experiments/probes/fused_planning.sh OUT [HIDDEN...]
set -uo pipefail
out=${1:-runs/fused_planning}
shift || true
sizes=${*:-64 128}
for h in $sizes; do
  for kernel in ${KERNELS:-xla pallas pallas-bf16}; do
    echo "== ${h} x 3, $kernel"
    timeout 150 python3 -m stride_jax.cli bench-mppi --robots go1 --models stride --samples 1024 \
      --horizons 30 --substeps 1 --shared-lnn --hidden "$h" --kernel "$kernel" --repeats 20 \
      --out "$out/h${h}_$kernel" 2>&1 | grep -E "K=|Error|error" | tail -3
  done
done
