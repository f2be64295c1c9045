#!/usr/bin/env bash
# The paper preset of experiments/reproduce.py on one GPU from the committed Table I checkpoints
# (results/models/<robot>/<model>-s0), in one device call of under 10 minutes:
#   1. the checkpoints go where experiments/table1.py writes its runs (runs/<robot>-paper/);
#   2. the Table I datasets are regenerated in the background with table1.py's command and seed
#      (unless present with the checkpoints' dataset_sha256), and checked against it;
#   3. meanwhile the pendulum runs train side by side (reproduce.py --parallel);
#   4. the legged parts run on seed 0 (the horizon part reads Table I's own files, every seed).
# Usage (repository root): bash experiments/reproduce_paper.sh [PARTS] [ROBOTS]
set -euo pipefail
parts=${1:-phase,allocation,nfe,forces}
robots=${2:-go1,g1}
export XLA_PYTHON_CLIENT_PREALLOCATE=false
pick() { tr ',' '\n' <<<"$parts" | grep -xE "$1" | paste -sd, || true; }
mkdir -p logs
trained_on() { python3 -c 'import json, sys; print(json.load(open(sys.argv[1]))[sys.argv[2]])' "$@"; }
pids=()
for r in ${robots//,/ }; do
  # Fresh copies of each run's files and its best checkpoint alone: a device's copy of the tree
  # may keep files deleted here since an earlier call (checkpoints of older code, say).
  rm -rf "runs/$r-paper"
  for m in results/models/$r/*/; do
    run="runs/$r-paper/$(basename "$m")" && step=$(trained_on "$m/summary.json" best_step)
    mkdir -p "$run/best" && cp "$m"/*.json "$run/" && cp -r "$m/best/$step" "$run/best/"
  done
  want=$(trained_on "results/models/$r/stride-s0/config.json" dataset_sha256)
  if [ ! -f "data/$r-paper/meta.json" ] ||
     [ "$(trained_on "data/$r-paper/meta.json" arrays_sha256)" != "$want" ]; then
    rm -rf "data/$r-paper"
    python3 -m stride_jax.cli data --robot "$r" --preset paper --episodes 1024 \
      --out "data/$r-paper" >"logs/data-$r.log" 2>&1 &
    pids+=($!)
  fi
done
pendulum=$(pick 'phase|allocation')
legged=$(pick 'nfe|forces|horizon')
if [ -n "$pendulum" ]; then
  python3 experiments/reproduce.py --preset paper --parallel 12 --parts "$pendulum"
fi
for p in "${pids[@]}"; do wait "$p"; done
python3 - "$robots" <<'PY'
import json, pathlib, sys
for robot in sys.argv[1].split(","):
    data = json.loads(pathlib.Path(f"data/{robot}-paper/meta.json").read_text())["arrays_sha256"]
    for run in sorted(pathlib.Path(f"runs/{robot}-paper").glob("*-s0")):
        trained = json.loads((run / "config.json").read_text())["dataset_sha256"]
        print(f"{run}: dataset {'identical to' if data == trained else 'DIFFERS from'} "
              "the one it was trained on", flush=True)
PY
if [ -n "$legged" ]; then
  python3 experiments/reproduce.py --preset paper --seeds 0 --robots "$robots" --parts "$legged"
fi
