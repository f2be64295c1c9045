#!/usr/bin/env bash
# Rows of the independent gap benchmark side by side, one process each (STRIDE_GAP_THREADS threads, 1 by default), for a
# machine with many CPU cores (a lent GPU machine's 16): `experiments/gap_one_row.py` per row,
# longest first (by the committed rows' seconds), no row started once less than MIN_S seconds
# are left before the deadline, each row killed at the deadline. Rows already in DONE (a folder of
# an earlier call's rows) are skipped, so the same command continues in the next call. Beside
# experiments/gap_bench_device.sh (the whole benchmark through its own pool, rows as it stores them):
# chosen rows, each with its whole diagnosis kept (to read why a verdict moved), longest first;
# experiments/gap_rows_collect.py then makes the benchmark's folder and tables of them.
#   bash experiments/gap_rows_parallel.sh OUT SECONDS "CASES" [DONE] [JOBS]
#   (PYTHON: the interpreter, python3 by default)
#   e.g. bash experiments/gap_rows_parallel.sh $OUT/rows 560 "$(seq -s ' ' 0 16)" results/gbi_partial 15
# Then: python experiments/gap_bench_compare.py results/gap_bench_go1_independent_cases ROWS --out ...
set -u
out=$1; seconds=$2; cases=$3; done_dir=${4:-}; jobs=${5:-$(nproc)}
MIN_S=${MIN_S:-150}
mkdir -p "$out"
deadline=$(( $(date +%s) + seconds ))
export STRIDE_GAP_THREADS=${STRIDE_GAP_THREADS:-1} OMP_NUM_THREADS=1 deadline MIN_S out PYTHON=${PYTHON:-python3}
todo=$(python3 - "$cases" "$done_dir" <<'EOF'
import json, pathlib, sys
cases, done = sys.argv[1].split(), sys.argv[2]
committed = pathlib.Path("results/gap_bench_go1_independent_cases")
rows = []
for c in cases:
    for noise in ("clean", "noisy"):
        name = f"{int(c):02d}-{noise}"
        if done and (pathlib.Path(done) / f"{name}.json").exists():
            continue
        f = committed / f"{name}.json"
        secs = json.loads(f.read_text())["row"].get("row_seconds", 0) if f.exists() else 1e9
        rows.append((secs, c, noise))
for secs, c, noise in sorted(rows, reverse=True):
    print(c, noise)
EOF
)
echo "$todo" | grep -c . | xargs echo "rows to run:"
echo "$todo" | xargs -P "$jobs" -L 1 bash -c '
  left=$(( deadline - $(date +%s) ))
  [ "$left" -lt "$MIN_S" ] && { echo "skip $0 $1 (${left} s left)"; exit 0; }
  flag=""; [ "$1" = noisy ] && flag=--noisy
  t0=$(date +%s)
  timeout "$left" ${PYTHON:-python3} experiments/gap_one_row.py --case "$0" $flag --out "$out" > "$out/log-$0-$1.txt" 2>&1
  echo "row $0 $1 rc=$? $(( $(date +%s) - t0 )) s: $(tail -1 "$out/log-$0-$1.txt" | cut -c1-220)"'
echo "done at $(date +%T)"
