#!/usr/bin/env bash
# MPPI step latency on one GPU with the rollouts split over CUDA streams (MPPIConfig.streams), with
# one network or two for L and V: Go1, K=1024, H=30, at the control rate, median of 20.
# Usage (repository root, on the GPU machine): bash experiments/mppi_gpu_streams.sh OUT
set -uo pipefail
out=${1:-runs/mppi_gpu_streams}
mkdir -p "$out"
python3 - <<'PY'
from stride_jax.control import bench
import jax
b = bench.setup("go1", "stride", 1024, 30, bench.BenchConfig(substeps=1, streams=4))
text = jax.jit(b.step).lower(b.state, b.q0, b.qd0).compile().as_text()
print("stream annotations in the compiled step:", text.count("_xla_stream_annotation"),
      "; async calls:", text.count("call-start"))
PY
for models in stride,delan; do
  for shared in no-shared-lnn shared-lnn; do
    for streams in 1 2 4 8; do
      echo "== $models --$shared --streams $streams"
      python3 -m stride_jax.cli bench-mppi --robots go1 --models "$models" --samples 1024 \
        --horizons 30 --substeps 1 --streams "$streams" --"$shared" --repeats 20 \
        --out "$out/$shared-streams$streams" 2>&1 | grep -E "K=|Error|error" | tail -3
    done
  done
done
