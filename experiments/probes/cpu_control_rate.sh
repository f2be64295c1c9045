#!/usr/bin/env bash
# The CPU planning rate of issue 4 (Go1, K=128, H=16, integrating at the control period) at the
# three network sizes, two and one network(s) for L and V, with the samples split over one XLA
# host device per core (STRIDE_HOST_DEVICES). Usage (repository root): bash experiments/probes/cpu_control_rate.sh [OUT]
set -euo pipefail
out=${1:-results/mppi_latency/control_rate}
export STRIDE_HOST_DEVICES=${STRIDE_HOST_DEVICES:-auto}
stride() { python3 -m stride_jax.cli "$@" 2>&1 | grep -E "K=|rror"; }
stride bench-mppi --preset target-coarse --repeats 20 --out "$out"
for h in 128 64; do
  stride bench-mppi --preset target-small --hidden "$h" --repeats 20 --out "$out/h$h"
  stride bench-mppi --preset target-small --hidden "$h" --shared-lnn --repeats 20 --out "$out/h$h-shared"
done
