#!/usr/bin/env bash
# Table I on a lent GPU machine: carried wheels and Menagerie, data, every model x seeds (plus
# STRIDE ablations), evaluation; tables, training curves and the seed-0 checkpoints land in OUT,
# the driver's log as it goes. Usage (repository root, on the GPU machine, with .whl and
# .menagerie carried):
#   bash experiments/table1_device.sh OUT ROBOT STEPS TRAIN_MINUTES [ABLATION [EXTRA...]]
# EXTRA goes to experiments/table1.py: --eval-only in a second call on the same (warm) machine
# evaluates what the first trained.
set -uo pipefail
out=$1; robot=$2; steps=$3; minutes=$4; ablation=${5:-}; shift 5 || shift $#
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
  --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1
tar -C .menagerie -xJf .menagerie/menagerie.tar.xz && export MENAGERIE_ROOT=$PWD/.menagerie/menagerie
root=/tmp/table1
mkdir -p "$out/$robot"
python3 experiments/table1.py --robot "$robot" --preset paper --parallel 17 --steps "$steps" \
  --minutes "$minutes" --ablation "$ablation" --root "$root" --out "$out/$robot" "$@" 2>&1 |
  grep --line-buffered -v -i "warp\|warn" | tee "$out/${robot}_driver.log" | tail -40
runs=$root/runs/$robot-paper
(cd "$runs" && tar -cJf "$out/${robot}_logs.tar.xz" */metrics.csv */train.log */summary.json \
  $(ls */eval.log 2>/dev/null))
[ -f "$out/$robot/table.md" ] &&
  (cd "$runs" && tar -cJf "$out/${robot}_models_s0.tar.xz" --exclude=ckpt --exclude=eval_out *-s0)
ls -la "$out" "$out/$robot"
