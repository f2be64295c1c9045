#!/usr/bin/env bash
# Is `stride data` run-to-run identical on this machine? Simulates one dataset twice with XLA's
# deterministic GPU ops (the data job's default since they exist) and twice without
# (STRIDE_DETERMINISTIC=0), and prints each arrays.npz's sha256 and generation time (compilation
# included; the second of each pair reuses the first's compiled programs from the cache).
#   bash experiments/probes/data_determinism.sh OUT ROBOT EPISODES [more `stride data` flags]
# e.g. bash experiments/probes/data_determinism.sh /tmp/det go1 256 --stochastic \
#        --policy results/policies/ppo_go1 --action-noise 0.3        # Table I's walking data
set -u
out=$1 robot=$2 episodes=$3
shift 3
work=$(mktemp -d)
export JAX_COMPILATION_CACHE_DIR=$work/cache
mkdir -p "$out"
echo "deterministic sha256 generation_s ($robot, $episodes episodes, flags: $*)" | tee "$out/determinism.txt"
i=0
for mode in 1 1 0 0; do
  i=$((i + 1))
  STRIDE_DETERMINISTIC=$mode python3 -m stride_jax.cli data --robot "$robot" --preset paper \
    --episodes "$episodes" "$@" --out "$work/d$i" > "$work/d$i.log" 2>&1 \
    || { tail -5 "$work/d$i.log"; exit 1; }
  python3 -c "import json; m = json.load(open('$work/d$i/meta.json')); \
print('$mode', m['arrays_sha256'][:16], round(m['generation_seconds'], 1))" | tee -a "$out/determinism.txt"
done
rm -rf "$work"
