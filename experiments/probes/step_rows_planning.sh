#!/usr/bin/env bash
# The planner with the whole-step kernel in programs of 16 and of 8 samples (fused_step.ROWS;
# the default, fused_step.program_rows, picks 8 where 16-row programs leave SMs idle), Go1 or G1
# STRIDE NFE 2, one network for L and V, bfloat16 products, K samples, H = 30, median of 20, each
# in its own run. Usage (repository root, on the GPU machine):
#   bash experiments/probes/step_rows_planning.sh OUT ROBOT K HIDDEN...
set -uo pipefail
out=$1; robot=$2; k=$3; shift 3
for h in "$@"; do
  for rows in 16 8; do
    echo "== $robot ${h} x 3, K=$k, $rows rows per program"
    timeout 150 python3 -c "import sys; from stride_jax.dynamics import fused_step
fused_step.ROWS = int(sys.argv[1]); sys.argv = ['stride'] + sys.argv[2:]
from stride_jax import cli; cli.main()" "$rows" bench-mppi --robots "$robot" --models stride \
      --samples "$k" --horizons 30 --substeps 1 --shared-lnn --hidden "$h" --kernel pallas-step-bf16 \
      --repeats 20 --out "$out/${robot}_h${h}_k${k}_rows${rows}" 2>&1 | grep -E "K=|Error|error" | tail -3
  done
done
