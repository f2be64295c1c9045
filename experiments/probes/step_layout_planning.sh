#!/usr/bin/env bash
# The planner with the whole-step kernel at given program layouts (samples and warps per program:
# fused_step.ROWS, fused_step.WARPS; 0 warps: the default), or through XLA (float32 or bfloat16
# products): STRIDE NFE 2, one network for L and V, K samples, H = 30, median of 20, each layout
# in its own run, into OUT/<robot>_h<HIDDEN>_k<K>_<rows R[_warps W][_block B] | xla | xla-bf16>.
# A third field gives the small loops' columns per iteration (fused_step.BLOCK, as the probes'
# --block: N for every loop, or name=N,...; none: the library's default, blocks of 4 since session
# 83, so a run before it reads as ROWS:WARPS:1). A fourth field, 0 or 1, factorises the reduced
# system whole or in two halves (fused_step.SPLIT; none: the library's default, halves since
# session 84). Usage (repository root, on the GPU machine):
#   bash experiments/probes/step_layout_planning.sh OUT ROBOT K HIDDEN LAYOUT...   # LAYOUT: ROWS:WARPS[:BLOCK[:SPLIT]], xla or xla-bf16
set -uo pipefail
out=$1; robot=$2; k=$3; h=$4; shift 4
for layout in "$@"; do
  block=""; split=""
  if [ "${layout#xla}" != "$layout" ]; then rows=0; warps=0; kernel=$layout; name=$layout
  else
    IFS=: read -r rows warps block split <<<"$layout"
    kernel=pallas-step-bf16; name=rows${rows}
    [ "$warps" = 0 ] || name=${name}_warps${warps}
    [ -z "$block" ] || name=${name}_block${block//[=,]/-}
    [ -z "$split" ] || name=${name}_split${split}
  fi
  echo "== $robot ${h} x 3, K=$k, $name"
  timeout 150 python3 -c "import sys; from stride_jax.dynamics import fused_step
from experiments.probes.fused_step_check import parse_blocks
r, w = int(sys.argv[1]), int(sys.argv[2])
fused_step.ROWS = r or None
fused_step.WARPS = w or fused_step.WARPS
fused_step.BLOCK = parse_blocks(sys.argv[3]) if sys.argv[3] else fused_step.BLOCK
fused_step.SPLIT = bool(int(sys.argv[4])) if sys.argv[4] else fused_step.SPLIT
sys.argv = ['stride'] + sys.argv[5:]
from stride_jax import cli; cli.main()" "$rows" "$warps" "$block" "$split" bench-mppi --robots "$robot" --models stride \
    --samples "$k" --horizons 30 --substeps 1 --shared-lnn --hidden "$h" --kernel "$kernel" \
    --repeats 20 --out "$out/${robot}_h${h}_k${k}_${name}" 2>&1 | grep -E "K=|Error|error" | tail -3
done
