#!/usr/bin/env bash
# Table I on a lent GPU machine: carried wheels and Menagerie, data, every model x seeds (plus
# STRIDE ablations), evaluation. What comes back, in OUT (a device call returns at most 8 files):
# NAME_driver.log as it goes, then NAME.tar.xz (in 15 MiB parts NAME.tar.xz.part.* where larger:
# a call returns files of at most 16 MiB) with the table (md, json), every run's
# metrics.csv / train.log / summary.json / eval.log and the seed-0 checkpoints, where NAME is
# ROBOT or ROBOT_DATA. Usage (repository root, on the GPU machine, with .whl and .menagerie
# carried: the cp312 wheels, or .whl/site.tar.xz, them installed into a folder and packed):
#   [DATA=walk] bash experiments/table1_device.sh OUT ROBOT STEPS TRAIN_MINUTES [ABLATION [EXTRA...]]
# DATA picks experiments/table1.py's --data (explore: default); DATA_POLICY (with DATA=walk) its
# --data-policy, and NAME gains _<the policy folder's name>; TW (when set and not 0) its
# --transition-weight, and NAME gains _twTW; TF (below 1, with TW) its --transition-fraction, and
# NAME gains _tfTF; BW (when set and not 1, with TW) its --base-weight, and NAME gains _bwBW; POT (when set and not net) its --potential, and NAME gains _POT (com: the
# prior's potential in gravity's multibody form); SLOPE (when set and not 0) its --slope-deg
# (sloped data, every model told the slope), and NAME gains _slopeSLOPE; two calls with different DATA
# may run side by side (they share the compilation cache). LIMIT_S stops the driver after that
# many seconds (0: never), so that what it made is still packed inside the device call's limit. EXTRA goes to experiments/table1.py:
# --eval-only in a second call on the same (warm) machine evaluates what the first trained.
# KEEP_SEEDS=all brings back every run's checkpoint (best/), not only seed 0's: closed-loop runs
# over trained seeds in a later session then need no retraining (G1: ~2 MB a run).
# TAG (when set) is added to NAME: two calls of one data set side by side (one model per GPU)
# then keep their tables and archives apart.
set -uo pipefail
out=$1; robot=$2; steps=$3; minutes=$4; ablation=${5:-}; shift 5 || shift $#
# the data's folder suffix and the training variant's, as experiments/table1.py names them
data=${DATA:-explore}; dargs=(); dsuffix=""
[ "$data" = explore ] || dsuffix=_$data
dpol=${DATA_POLICY:-}
if [ -n "$dpol" ]; then dargs=(--data-policy "$dpol"); dsuffix=${dsuffix}_$(basename "$dpol"); fi
slope=$(printf '%g' "${SLOPE:-0}")  # numbers as table1.py writes them (%g: 1.0 -> 1)
if [ "$slope" != 0 ]; then dargs+=(--slope-deg "$slope"); dsuffix=${dsuffix}_slope$slope; fi
tw=$(printf '%g' "${TW:-0}"); tf=$(printf '%g' "${TF:-1}"); pot=${POT:-net}; vargs=(); vsuffix=""
if [ "$tw" != 0 ]; then vargs=(--transition-weight "$tw"); vsuffix=_tw$tw; fi
if [ "$tw" != 0 ] && [ "$tf" != 1 ]; then vargs+=(--transition-fraction "$tf"); vsuffix=${vsuffix}_tf$tf; fi
bw=$(printf '%g' "${BW:-1}")
if [ "$bw" != 1 ]; then vargs+=(--base-weight "$bw"); vsuffix=${vsuffix}_bw$bw; fi
if [ "$pot" != net ]; then vargs+=(--potential "$pot"); vsuffix=${vsuffix}_$pot; fi
name=$robot$dsuffix$vsuffix
runs_name=$robot$dsuffix$vsuffix-paper  # the runs folder experiments/table1.py makes
# NAMES_ONLY=1: print the archive's NAME and the runs folder's name, nothing run (tested against
# experiments/table1.py's folder_suffixes)
[ "${NAMES_ONLY:-0}" = 1 ] && { echo "$name $runs_name"; exit 0; }
# the carried site and Menagerie, unpacked once per machine (two calls side by side take turns)
( flock 9; source experiments/device_env.sh ) 9>/tmp/table1_setup.lock || exit 1
source experiments/device_env.sh || exit 1  # (unpacked now: exports the jobs' environment)
root=/tmp/table1
[ -z "${TAG:-}" ] || name=${name}_$TAG
res=/tmp/table1_results/$name
mkdir -p "$res"
timeout -s INT "${LIMIT_S:-0}" python3 experiments/table1.py --robot "$robot" --data "$data" \
  --preset paper --parallel 17 \
  --steps "$steps" --minutes "$minutes" --ablation "$ablation" --root "$root" --out "$res" "${dargs[@]}" "${vargs[@]}" "$@" \
  2>&1 | grep --line-buffered -v -i "warp\|warn" | tee "$out/${name}_driver.log" | tail -40
keep='*-s0'; [ "${KEEP_SEEDS:-0}" = all ] && keep='*'  # whose checkpoints come back (best/, configs)
runs=$root/runs/$runs_name
(cd "$runs" && tar -cf "$res/runs.tar" */metrics.csv */train.log */summary.json \
  $(ls */eval.log 2>/dev/null) && tar -rf "$res/runs.tar" --exclude=ckpt --exclude=eval_out $keep)
tar -C "$res" -cJf "$out/$name.tar.xz" .
# a device call returns files of at most 16 MiB: a larger archive comes back in 15 MiB parts
# (join: cat NAME.tar.xz.part.* > NAME.tar.xz)
if [ "$(stat -c %s "$out/$name.tar.xz")" -gt $((15 * 1024 * 1024)) ]; then
  split -b 15m "$out/$name.tar.xz" "$out/$name.tar.xz.part." && rm "$out/$name.tar.xz"
fi
ls -la "$out" "$res"
