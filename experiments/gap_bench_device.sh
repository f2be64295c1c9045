#!/usr/bin/env bash
# The independent gap benchmark (stride gap bench-independent --preset default) on a lent many-core
# machine, in calls of at most 10 minutes: rows finished in earlier calls are resumed from .bench/
# (ignored; kept while the machine stays warm) or from the tgz of the last call (carry it back in
# .bench_prev.tgz), rows still running at the limit are lost and rerun by the next call.
#   bash experiments/gap_bench_device.sh OUT_TGZ LIMIT_S WORKERS THREADS
# Needs PYTHONPATH (the cp312 site and the repo) and MENAGERIE_ROOT set (docs/reproduce.md).
set -u
out=$1; limit=$2; workers=$3; threads=$4
mkdir -p .bench
if [ -f .bench_prev.tgz ] && [ ! -d .bench/gap_bench_go1_independent_cases ]; then tar -C .bench -xzf .bench_prev.tgz; fi
echo "rows before: $(ls .bench/gap_bench_go1_independent_cases 2>/dev/null | wc -l); cores $(nproc)"
timeout -s INT "$limit" python -m stride_jax.cli gap bench-independent --preset default --workers "$workers" \
  --threads "$threads" --out .bench 2>&1 | grep -v "it/s\]\|s/it\]" | tail -60
pkill -f multiprocessing.spawn || true  # pool workers left by the timeout
echo "rows after: $(ls .bench/gap_bench_go1_independent_cases | wc -l)"
tar -C .bench -czf "$out" .
