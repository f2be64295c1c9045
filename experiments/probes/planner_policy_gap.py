"""How far a planner's applied action is from the policy's own action at the same state, step by
step, in one closed-loop episode: the size of the perturbation the planner puts on the policy's
walk (compare ``experiments/probes/policy_noise.py``: the walk under i.i.d. action noise).

Every flag but ``--gap-out`` is the closed-loop job's (``python -m stride_jax.jobs.closed_loop``);
run one model, one scenario, one episode, e.g. G1's STRIDE planner at its GPU settings:

    python experiments/probes/planner_policy_gap.py --gap-out results/planning_diagnosis/planner_policy_gap_g1_lowf \\
        --preset gpu --robot g1 --policy results/policies/ppo_g1 --learned results/learned_g1/reward_value.msgpack \\
        --mppi.policy-samples 128 --mppi.family-samples 384 --mppi.prior-fraction 1.0 --prior-noise-std 0.05 \\
        --mppi.family-decay 0.8 --planning.observer-gain 0.1 --planning.learned-track-weight 10 \\
        --planning.trust-limit 3.5 --planning.trust-hold-s 1.0 --govern \\
        --models stride=results/models/g1_walk_tw1_tf0.25_b/stride-s0 --scenarios low_friction \\
        --seconds 1.2 --out /tmp/ppg

Per control step: the root mean square over the action's entries of (planner's action - the
policy's action, both clipped to the planner's bounds), in the planner's action units (the
noise std of ``policy_noise.py`` is the same measure for i.i.d. noise), and the planner's status.
On a CPU a G1 planner step at K=1024 takes ~4.5 s: a second of episode is ~4 minutes.
"""

from __future__ import annotations

import json
import pathlib
import sys

import jax
import jax.numpy as jnp
import numpy as np

from stride_jax import config, io
from stride_jax.jobs import closed_loop as cl


def main() -> None:
    argv = sys.argv[1:]
    if "--gap-out" not in argv:
        raise SystemExit("--gap-out STEM is required (the other flags are the closed-loop job's)")
    i = argv.index("--gap-out")
    stem = pathlib.Path(argv[i + 1])
    argv = argv[:i] + argv[i + 2:]
    steps: list[tuple[float, float, int, bool]] = []
    control_dt: list[float] = []
    original = cl.run_episode

    def with_gap(sm, mx_sim, slots, planning, planner, *args, **kw):
        control_dt.append(sm.robot.ctrl_dt)
        if planner is None:
            return original(sm, mx_sim, slots, planning, planner, *args, **kw)
        lo, hi = jnp.asarray(planning.lo), jnp.asarray(planning.hi)

        def record(q_aug, qd, u, info, q_next, qd_next, down, key):
            gap = u - jnp.clip(planning.policy(q_aug, qd), lo, hi)
            rms, biggest = jnp.sqrt(jnp.mean(gap ** 2)), jnp.max(jnp.abs(gap))
            jax.debug.callback(lambda r, m, s, d: steps.append((float(r), float(m), int(s), bool(d))),
                               rms, biggest, info.status, down, ordered=True)
            return jnp.zeros(())

        trace, _ = original(sm, mx_sim, slots, planning, planner, *args, record=record, **kw)
        return trace

    cl.run_episode = with_gap
    config.config_main("experiments/probes/planner_policy_gap.py", cl.ClosedLoopConfig, cl.PRESETS,
                       cl.run, argv)
    if not steps:
        raise SystemExit("no planner steps recorded (a policy-only model, or every pair was already "
                         "in --out: use a fresh --out)")
    rms = np.array([s[0] for s in steps])
    up = ~np.array([s[3] for s in steps])
    dt = control_dt[0]
    lines = ["# How far the planner's action is from the policy's", "",
             f"`python experiments/probes/planner_policy_gap.py --gap-out {stem} {' '.join(argv)}`",
             "", "RMS over the action's entries of (planner - policy) per control step, while upright "
             "(the policy acting under the trust gate: 0):", "",
             "| window (s) | steps | median | 90th percentile | max |", "|---|---:|---:|---:|---:|"]
    edges = list(np.arange(0.0, len(steps) * dt + 1e-9, 0.4))
    for a, b in zip(edges[:-1], edges[1:]):
        sel = up[int(a / dt):int(b / dt)]
        r = rms[int(a / dt):int(b / dt)][sel]
        if r.size:
            lines.append(f"| {a:.1f}-{b:.1f} | {r.size} | {np.median(r):.4f} | "
                         f"{np.percentile(r, 90):.4f} | {r.max():.4f} |")
    io.atomic_write_text(stem.with_suffix(".md"), "\n".join(lines) + "\n")
    io.atomic_write_text(stem.with_suffix(".json"), json.dumps(dict(
        argv=argv, dt=dt, steps=[dict(rms=s[0], max=s[1], status=s[2], fallen=s[3]) for s in steps]),
        indent=1))
    print(f"wrote {stem}.{{md,json}}")


if __name__ == "__main__":
    main()
