#!/usr/bin/env bash
# The controller's own computation per control period (`stride closed-loop`'s controller_ms:
# the planner's step and the observer, no simulated world) of the headline closed-loop planners,
# and of variants of STRIDE's: each variant a one-period episode (what is timed is the
# controller, after it) through experiments/closed_loop_targets.sh, its rows under
# OUT/<variant>/, a summary in OUT/controller_time.md. Usage (repository root, on the GPU):
#   bash experiments/probes/controller_time.sh OUT ROBOT MODELS_DIR "FLAGS" VARIANT...
# VARIANT: NAME=MODELS:extra flags joined by '+', e.g. base=policy,stride,delan,onn
#   sub1=stride:--model-substeps+1 bf16=stride:--kernel+pallas-bf16
set -uo pipefail
out=$1 robot=$2 dir=$3 flags=$4; shift 4
mkdir -p "$out"
for v in "$@"; do
  name=${v%%=*} rest=${v#*=}
  models=${rest%%:*} extra=""
  [ "$rest" = "$models" ] || extra=${rest#*:}
  echo "== $name: $models ${extra//+/ }"
  # shellcheck disable=SC2086
  CHUNK_S=0 MODELS_DIR=$dir bash experiments/closed_loop_targets.sh "$robot" "$out/$name" 300 \
    "$models" walk --seconds 0.02 --controller-repeats 20 --progress-s 0 $flags ${extra//+/ } \
    | grep -E "controller|ms/step|rror" | grep -v "^  walk .*compiling"
done
python3 - "$out" "$@" <<'PY'
import json, pathlib, sys
out = pathlib.Path(sys.argv[1])
# (the rows' ms_per_step, of one-period episodes, is first-call overhead: not shown)
lines = ["| variant | model | controller ms per period (median) | longest |",
         "|---|---|---:|---:|"]
for v in sys.argv[2:]:
    name = v.split("=")[0]
    f = out / name / "closed_loop.json"
    if not f.is_file():
        lines.append(f"| {name} | (no rows) | - | - |")
        continue
    for r in json.loads(f.read_text())["rows"]:
        longest = r.get("controller_ms_max")
        lines.append(f"| {name} | {r['model']} | {r['controller_ms']:.1f} | "
                     + (f"{longest:.1f} |" if longest is not None else "- |"))
(out / "controller_time.md").write_text("\n".join(lines) + "\n")
print("\n".join(lines))
PY
