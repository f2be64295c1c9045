"""Is the policy's own walk at a knife edge in a scenario? The PPO policy alone, its action
perturbed each control step by Gaussian noise (the planner samples around the policy's actions;
this is the simplest such controller), over many draws: how many fall, and when, and how many
run past the command (``--over``: a policy's creep up a slope, session 92).

    python experiments/probes/policy_noise.py --robot g1 --policy results/policies/ppo_g1 \\
        --scenario low_friction --noise 0,0.05,0.1,0.2 --draws 16 --seconds 3 \\
        --out results/planning_diagnosis/policy_noise_g1_lowf

The noise is in the planner's action units (``planning.lo``/``hi``: G1's planner samples its
policy prior with std 0.05 there, ``closed_loop_targets.sh``); the action is clipped to the
bounds as the planner's is. Runs on a CPU (the draws vmapped; MJX there: tens of seconds).
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np

from stride_jax import io
from stride_jax.control import mppi, ppo
from stride_jax.control.episode import run_episode, scenario_world
from stride_jax.control.planning import PlanningConfig, make_planning
from stride_jax.jobs.closed_loop import ClosedLoopConfig, scenario
from stride_jax.sim import model as sim_model


def noisy_policy(planning, std: float, ar: float = 0.0) -> mppi.Planner:
    """A one-step "planner" that applies the policy's action plus noise of std ``std`` per entry:
    i.i.d. per step (``ar`` 0) or AR(1), ``e_t = ar e_(t-1) + sqrt(1 - ar^2) std xi_t`` (as
    smooth as a plan's noise; the state's ``plan`` row carries ``e``)."""
    lo, hi = jnp.asarray(planning.lo), jnp.asarray(planning.hi)

    def init(key, plan=None):
        return mppi.MPPIState(jnp.zeros((1, len(planning.lo))), key)

    def step(state, q, qd):
        key, k = jax.random.split(state.key)
        e = ar * state.plan[0] + jnp.sqrt(1 - ar ** 2) * std * jax.random.normal(k, lo.shape)
        u = jnp.clip(planning.policy(q, qd) + e, lo, hi)
        z = jnp.zeros(1)
        info = mppi.Info(z, z, z[0], u[None], jnp.zeros((), jnp.int32), u[None, None], z,
                         jnp.ones(1, jnp.int32), jnp.zeros((), bool))
        return u, mppi.MPPIState(e[None], key), info

    return mppi.Planner(init, step)


def draw_stats(t, fallen, v_base, command, over: float) -> dict:
    """What the probe reports of its draws, from their traces (``t`` ``[T]`` s, ``fallen``
    ``[D, T]``, ``v_base`` and ``command`` ``[D, T, 3]``): how many fell and when, the median
    forward speed at 1 s, how many ran more than ``over`` m/s past the command's forward speed
    while upright (a policy's creep), and the median of the last second's mean forward speed
    over the draws that stood (None where none did: a fallen draw's last second is its fall)."""
    fall = [float(t[f.argmax()]) if f.any() else None for f in fallen]
    per_s = int(round(1.0 / (t[1] - t[0])))
    excess = np.where(fallen, -np.inf, v_base[..., 0] - command[..., 0])
    stood = ~fallen.any(axis=1)
    return dict(falls=sum(f is not None for f in fall), fall_s=[f for f in fall if f is not None],
                vx_at_1s=float(np.median(v_base[:, per_s - 1, 0])), over=over,
                overspeed=int((excess.max(axis=1) > over).sum()),
                vx_last_s=float(np.median(v_base[stood, -per_s:, 0].mean(axis=1)))
                if stood.any() else None)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--robot", default="g1")
    ap.add_argument("--policy", required=True)
    ap.add_argument("--scenario", default="low_friction")
    ap.add_argument("--noise", default="0,0.05,0.1")
    ap.add_argument("--ar", type=float, default=0.0,
                    help="AR(1) coefficient of the noise per control step (0: i.i.d.)")
    ap.add_argument("--draws", type=int, default=16)
    ap.add_argument("--seconds", type=float, default=3.0, help="episode length (0: the scenario's)")
    ap.add_argument("--slope-deg", type=float, default=0.0, help="as the closed-loop job's")
    ap.add_argument("--rough-cm", type=float, default=0.0, help="as the closed-loop job's")
    ap.add_argument("--payload", type=float, default=0.0, help="as the closed-loop job's")
    ap.add_argument("--payload-body", default="", help="as the closed-loop job's")
    ap.add_argument("--govern", action=argparse.BooleanOptionalAction, default=True)
    ap.add_argument("--sense-gravity", action=argparse.BooleanOptionalAction, default=True,
                    help="the policy observes the scenario's gravity (as the closed loop's "
                         "--sense-gravity; the probes before session 46 ran without)")
    ap.add_argument("--over", type=float, default=0.25,
                    help="count draws whose forward speed passed the command by more than this "
                         "(m/s) while upright")
    ap.add_argument("--out", required=True, help="output stem (.md, .json)")
    a = ap.parse_args()
    if not 0 <= a.ar < 1:
        raise SystemExit(f"--ar {a.ar}: the AR(1) coefficient must be in [0, 1)")
    policy, _, env_cfg = ppo.load_policy(a.policy)
    if env_cfg.robot != a.robot:
        raise SystemExit(f"the policy {a.policy} drives {env_cfg.robot}, not {a.robot}")
    cfg = ClosedLoopConfig(robot=a.robot, seconds=a.seconds, govern=a.govern,
                           slope_deg=a.slope_deg, rough_cm=a.rough_cm, payload=a.payload,
                           payload_body=a.payload_body)
    sm = sim_model.load(a.robot)
    sc = scenario(cfg, a.scenario)
    w = scenario_world(sm, sc)
    limits = env_cfg.commands.bounds() if a.govern else None
    planning = make_planning(PlanningConfig(), env_cfg, sm, lambda q, qd, u, k: (q, qd), policy)

    def episode(std, key):
        return run_episode(w.sm, w.mx, w.slots, planning, noisy_policy(planning, std, a.ar),
                           w.n_steps, w.starts, w.values, key, pushes=w.pushes, limits=limits,
                           tilt=w.tilt, sense_gravity=a.sense_gravity)

    run = jax.jit(jax.vmap(episode, in_axes=(None, 0)))
    keys = jax.vmap(jax.random.key)(jnp.arange(a.draws))
    rows = []
    for std in (float(s) for s in a.noise.split(",")):
        t0 = time.perf_counter()
        tr = jax.tree.map(np.asarray, run(jnp.asarray(std), keys))
        rows.append(dict(noise=std, draws=a.draws,
                         **draw_stats(tr.t[0], tr.fallen, tr.v_base, tr.command, a.over)))
        print(f"noise {std}: {rows[-1]['falls']} of {a.draws} fell "
              f"({time.perf_counter() - t0:.0f} s)", flush=True)
    out = pathlib.Path(a.out)
    extra = "".join(f" --{k} {v:g}" for k, v in (("ar", a.ar), ("slope-deg", a.slope_deg),
                                                   ("rough-cm", a.rough_cm),
                                                   ("payload", a.payload)) if v)
    extra += f" --payload-body {a.payload_body}" if a.payload_body else ""
    extra += ("" if a.govern else " --no-govern") + ("" if a.sense_gravity
                                                     else " --no-sense-gravity")
    cmd = ("python experiments/probes/policy_noise.py --robot {} --policy {} --scenario {} "
           "--noise {}{} --draws {} --seconds {} --over {} --out {}").format(
        a.robot, a.policy, a.scenario, a.noise, extra, a.draws, a.seconds, a.over, a.out)
    io.atomic_write_text(out.with_suffix(".json"), json.dumps(
        dict(command=cmd, scenario=sc.name, ar=a.ar, rows=rows), indent=1))
    kind = f"AR(1) noise, coefficient {a.ar:g} per step" if a.ar else "i.i.d. noise"
    lines = [f"# The {a.robot} policy alone with action noise: {sc.name} ({kind})", "", f"`{cmd}`", "",
             "| noise std | fell | fall times (s) | median forward velocity at 1 s (m/s) "
             f"| over the command by > {a.over:g} m/s "
             "| median forward velocity in the last second, draws that stood |",
             "|---:|---:|---|---:|---:|---:|"]
    lines += [f"| {r['noise']:g} | {r['falls']} of {r['draws']} | "
              f"{', '.join(f'{f:.2f}' for f in r['fall_s']) or '-'} | {r['vx_at_1s']:.2f} | "
              f"{r['overspeed']} of {r['draws']} | "
              + ("-" if r["vx_last_s"] is None else f"{r['vx_last_s']:.2f}") + " |" for r in rows]
    io.atomic_write_text(out.with_suffix(".md"), "\n".join(lines) + "\n")
    print(f"wrote {out}.{{md,json}}")


if __name__ == "__main__":
    main()
