#!/usr/bin/env bash
# The planner with the whole-step kernel in programs of 16 and of 8 samples (fused_step.ROWS;
# the default, fused_step.program_rows, picks 8 where 16-row programs leave SMs idle), Go1 or G1
# STRIDE NFE 2, one network for L and V, bfloat16 products, K samples, H = 30, median of 20, each
# in its own run (step_layout_planning.sh at layouts 16:0 and 8:0, the default warps). Usage
# (repository root, on the GPU machine):
#   bash experiments/probes/step_rows_planning.sh OUT ROBOT K HIDDEN...
set -uo pipefail
out=$1; robot=$2; k=$3; shift 3
for h in "$@"; do
  bash "$(dirname "$0")/step_layout_planning.sh" "$out" "$robot" "$k" "$h" 16:0 8:0
done
