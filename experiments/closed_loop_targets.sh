#!/usr/bin/env bash
# Issue 19's closed-loop runs on one GPU, one process (several processes on one GPU time-slice
# it: measured 2-3x slower per control step each, results/closed_loop_go1_gpu/README.md); to fill
# the GPU, --episodes N runs a pair's draws side by side and --together the level scenarios too
# (one program per model, each episode in its own world; docs/control.md, closed loop).
#   bash experiments/closed_loop_targets.sh ROBOT OUT LIMIT_S MODELS SCENARIOS [more flags]
# e.g. bash experiments/closed_loop_targets.sh g1 /tmp/g1 540 policy,stride,delan,onn slope,soft
# MODELS: policy, oracle, NAME=RUN, or names of results/models/ROBOT/<name>-s0 (MODELS_DIR=g1_walk:
# of results/models/g1_walk/, the models trained on walking data). Rows are written as they
# finish and the driver skips the pairs already in OUT/closed_loop.json (re-run to resume); the
# whole folder ends as OUT.tgz (the device returns few files). Episodes run in chunks of
# CHUNK_S simulated seconds (default 1; 0: one program each), their state saved in OUT/partial
# after each: a call cut by its limit keeps what it ran, and the same command on the same OUT
# (this call's tgz unpacked there on a later machine, or the same warm machine) resumes at the
# last chunk instead of losing the model's whole episode (sessions 59-61 lost three so).
# RESUME=PATH/OUT.tgz: that tgz, from an earlier call cut on another machine and carried here, is
# unpacked beside OUT first where OUT does not exist yet (sessions 63-64 did this by hand).
set -u
robot=$1 out=$2 limit=$3 names=$4 scen=$5
shift 5
if [ -n "${RESUME:-}" ] && [ ! -e "$out" ]; then
  [ -f "$RESUME" ] || { echo "closed_loop_targets: RESUME=$RESUME: no such file" >&2; exit 2; }
  mkdir -p "$(dirname "$out")" && tar -C "$(dirname "$out")" -xzf "$RESUME" || exit 2
  [ -d "$out" ] || { echo "closed_loop_targets: RESUME=$RESUME holds no folder $(basename "$out")/ (the tgz of another OUT?)" >&2; exit 2; }
  echo "closed_loop_targets: $out unpacked from $RESUME"
fi
models=""
for n in ${names//,/ }; do
  case $n in
    policy|oracle|nominal|*=*) models+="$n,";;
    *) models+="$n=results/models/${MODELS_DIR:-$robot}/$n-s0,";;
  esac
done
common=(--preset gpu --robot "$robot" --chunk-s "${CHUNK_S:-1}" --policy "results/policies/ppo_$robot"
        --learned "results/learned_$robot/reward_value.msgpack")
gate=3.5
for f in "$@"; do [ "$f" = --planning.model-gravity ] && gate=2.5; done
if [ "$robot" = go1 ]; then  # K = 1024: 64 policy, 256 command-family, 352 prior, 352 plan
  # observer gain 0.3 and tracking weight 30 since session 21 (results/closed_loop_go1_gpu/
  # parts/tw30_obs03; the rows @walk ran with 0.1 and 10)
  # No trust gate: G1's 2.5 (below), tried on Go1's sloped-data models in session 53, handed
  # 85-93% of the rough ground to the policy and lost the planner's gain there
  # (results/closed_loop_go1_gpu/gate25.md); a later --planning.trust-limit among the flags sets one.
  common+=(--mppi.policy-samples 64 --mppi.family-samples 256 --mppi.prior-fraction 0.5
           --prior-noise-std 0.08 --planning.observer-gain 0.3 --planning.learned-track-weight 30
           # integral action on the velocity error since session 67 (results/closed_loop_go1_gpu/
           # README.md, "Session 67": slope 0.060 -> 0.042, tilt 0.057 -> 0.042, rough 0.065 ->
           # 0.061 for STRIDE and alike for DeLaN and ONN; push 0.065 -> 0.067 for every kind, the
           # integral winding up in the recovery). The runs before it ran without: VI=0, or a later
           # --planning.velocity-integral 0 among the flags, reproduces them.
           $([ "${VI:-1}" = 1 ] && echo --planning.velocity-integral 1.0))
else  # G1: closer to the policy (the settings that kept G1 planners up before,
      # results/closed_loop/closed_loop_g1_gpu_policy_noise): 128 policy, 384 family, 512 prior
  common+=(--mppi.policy-samples 128 --mppi.family-samples 384 --mppi.prior-fraction 1.0
           --prior-noise-std 0.05 --mppi.family-decay 0.8 --planning.observer-gain 0.1
           --planning.learned-track-weight 10
           # the model-trust gate since session 41 (results/closed_loop_g1_gpu/trust_gate.md;
           # the runs before it ran without: TRUST=0 for those): 3.5 m/s^2 where the models are
           # not told the slope (a right model then needs g sin 15 deg = 2.5 of correction on the
           # tilt); 2.5 where they are (--planning.model-gravity; since session 51, chosen on the
           # tilt and kept out of sample: results/closed_loop_g1_gpu/gate25.md). A later
           # --planning.trust-limit among the flags wins; --planning.trust-delay-s D among them
           # hands over only once the trigger has held D s (sessions 86-87: at 0.2 s a gain
           # under pushes and a fall on the tilt in 1 of 24 draws; results/closed_loop_g1_gpu/
           # README.md, "Session 87").
           $([ "${TRUST:-1}" = 1 ] && echo --planning.trust-limit "$gate" --planning.trust-hold-s 1.0)
           # the stop prior since session 59 (results/closed_loop_g1_gpu/README.md, "Session 59":
           # the command changes 0.311 -> 0.296, nil at walking speeds; the runs before it ran
           # without: a later --planning.family-cost-stop 0 among the flags reproduces them)
           --planning.family-cost-stop 0.3
           # horizon 10 since session 88 (results/closed_loop_g1_gpu/README.md, "Session 88":
           # STRIDE and DeLaN track closer than at 20 in every scenario, STRIDE at most the
           # policy in 6 of 6 with no fall, where at 20 it lost the command changes and rough
           # ground; ONN loses on the tilt, 3 of 12 fell, soft ground and low friction); the
           # runs before it ran 20: a later --mppi.horizon 20 among the flags reproduces them)
           --mppi.horizon 10)
           # No velocity integral (Go1's since session 67): on G1 it gains on soft ground, rough
           # ground, low friction and the command changes but makes every kind fall on the 15
           # degree tilt (24 of 24 episodes) and loses on the push (results/closed_loop_g1_gpu/
           # README.md, "Session 69"); --planning.velocity-integral 1.0 among the flags runs it.
fi
mkdir -p "$out"
timeout "$limit" python -m stride_jax.jobs.closed_loop "${common[@]}" --models "${models%,}" \
  --scenarios "$scen" --out "$out" "$@" 2>&1 | grep -v "import warp\|import mujoco_warp" | tee -a "$out/run.log"
tar -czf "$out.tgz" -C "$(dirname "$out")" "$(basename "$out")"
# On a lent machine ($OUT set by the device tool) the tgz goes there at once: a later step of
# the same call that the call's own limit kills then loses only its own part (session 69 lost
# two finished parts, copied only at the call's end).
if [ -n "${OUT:-}" ] && [ -d "$OUT" ]; then cp "$out.tgz" "$OUT/"; fi
