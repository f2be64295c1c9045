"""Where a learned model goes wrong in a scenario: each trained model's one-control-period
prediction error along the PPO policy's own episode in the scenario's MJX world, before and after
a time split (e.g. flat ground, then the slope built up from 2 s) or between several (the
stretches of constant command), issue 19's "find why".

The closed-loop planner carries a disturbance observer: a constant base-acceleration offset
absorbs a model's steady bias (the slope's gravity component along the ground, which no model
trained on flat ground can know). What it cannot absorb is the error that varies from step to
step. So per model and phase this writes the bias (mean error of the base's linear acceleration
over one control period, m/s^2, per world axis: what the observer converges to), the spread
around it (RMS after removing the bias: what is left to the planner), and the joint-velocity
RMSE after one period (rad/s); STRIDE's residual is sampled ``--draws`` times per state.

    python experiments/scenario_model_error.py --robot g1 --scenario tilt --slope-deg 15 \\
        --models stride=results/models/g1_walk_tw1_tf0.25_b/stride-s0,... \\
        --out results/planning_diagnosis/g1_tilt15_model_error

``--model-gravity`` adds a row per model that takes a gravity direction, told the sensed one at
each state (as the closed loop's ``--planning.model-gravity``): what a Lagrangian model's turned
potential buys on an emulated slope. ``--prior`` adds, per model with a Lagrangian prior and a
residual (STRIDE, DeLaN + MLP), rows of its prior alone (the residual force left out; its own
trained prior, told the gravity where the model is): which part carries a bias. ``--govern``
clips the scenario's commands to the policy's training range (the closed loop's ``--govern``;
the policy alone falls in G1's ungoverned command changes).

Writes OUT.md and OUT.json (the command, per-model rows).
"""

from __future__ import annotations

import argparse
import pathlib
import shlex
import sys
import time

import numpy as np

import stride_jax


def episode(sm, sc, policy_path: str, govern: bool = False):
    """The policy of run ``policy_path`` alone in scenario ``sc``
    (:func:`stride_jax.control.episode.policy_alone`): ``(t, q, qd, ctrl, q2, qd2, fallen,
    down)`` per control period, numpy (``down``: the sensed gravity direction)."""
    import jax
    from stride_jax.control.episode import policy_alone
    from stride_jax.control.planning import split

    ep, _ = policy_alone(sm, sc, policy_path, govern)
    nq = sm.mj.nq
    down = jax.vmap(lambda qa: split(qa, nq).gravity)(ep.q_aug)
    return [np.asarray(x) for x in (ep.t, ep.q_aug[:, :nq], ep.qd, ep.ctrl, ep.q_next,
                                    ep.qd_next, ep.fallen, down)]


def prior_alone(model, params):
    """``(model, params)`` of a structured model's Lagrangian prior alone: the same prior
    networks and configuration, the residual force left out (``dynamics.models`` kind
    ``delan_prior``)."""
    from stride_jax.dynamics import models
    if model.residual in (None, "none"):
        raise ValueError(f"{model.name} has no residual to leave out")
    prior = models.structured("delan_prior", model.spec, model.actuation, model.config,
                              model.scales, residual="none")
    return prior, {"lnn": params["lnn"], "residual": {}}


def phase_errors(acc_err: np.ndarray, qd_err: np.ndarray, nu: int) -> dict:
    """``acc_err [T, draws, 3]`` (true minus predicted base linear acceleration over one period,
    m/s^2) and ``qd_err [T, draws, nv]`` of one phase -> bias, spread and joint RMSE."""
    per_step = acc_err.mean(axis=1)  # the draws' mean: what the planner's rollouts average
    bias = per_step.mean(axis=0)
    spread = np.sqrt(((per_step - bias) ** 2).mean(axis=0))
    joints = float(np.sqrt((qd_err[..., -nu:] ** 2).mean()))
    return dict(steps=int(acc_err.shape[0]), bias=bias.tolist(), spread=spread.tolist(),
                bias_norm=float(np.linalg.norm(bias)), spread_norm=float(np.linalg.norm(spread)),
                joint_vel_rmse=joints)


def one_period(step, q, qd, ctrl, down, draws: int, central: bool = False) -> np.ndarray:
    """``qd' [T, draws, nv]`` of ``step(q, qd, ctrl, key, down=...)`` (``learned_step``) at each
    of the ``T`` states, ``draws`` residual draws each (keys from ``key(0)``); ``central``: the
    residual's central sample (key None: a stochastic model's latent at its centre), one per
    state; ``down``: the gravity direction per state, or None (not told)."""
    import jax

    keys = jax.random.split(jax.random.key(0), (len(q), 1 if central else draws))
    told = down is not None
    down = down if told else np.zeros((len(q), 3), np.float32)
    over_draws = jax.vmap(lambda q, qd, u, k, g: step(q, qd, u, None if central else k,
                                                      down=g if told else None),
                          in_axes=(None, None, None, 0, None))
    _, qd_pred = jax.jit(jax.vmap(over_draws))(q, qd, ctrl, keys, down)
    return np.asarray(qd_pred, np.float64)


def phases(t: np.ndarray, splits: list[float]) -> dict[str, np.ndarray]:
    """The control periods' times ``t`` cut at ``splits`` (s, ascending): ``{label: mask}``,
    "before a s", "a-b s", ..., "from z s" (one split: before and from it)."""
    if not splits or any(b <= a for a, b in zip(splits, splits[1:])):
        raise SystemExit(f"--split-s {','.join(f'{x:g}' for x in splits)}: give one or more "
                         "times in ascending order")
    edges = [-np.inf, *splits, np.inf]
    out = {}
    for a, b in zip(edges, edges[1:]):
        label = (f"before {b:g} s" if a == -np.inf else f"from {a:g} s" if b == np.inf
                 else f"{a:g}-{b:g} s")
        out[label] = (t >= a) & (t < b)
    return out


def scenario(name: str, seconds: float, slope_deg: float = 0.0, rough_cm: float = 0.0):
    """The scenario ``name`` lasting ``seconds`` with the closed loop's overrides of its slope
    (degrees) and rough ground's bump height (cm) (``stride_jax.jobs.closed_loop.scenario``, which
    renames it so: ``tilt15``, ``rough2``; 0: keep); an unknown name, or an override the scenario
    has no use for (the closed loop passes those over: one run spans several scenarios), is an
    error naming it."""
    from stride_jax.control.scenarios import SCENARIOS
    from stride_jax.jobs import closed_loop

    if name not in SCENARIOS:
        raise SystemExit(f"--scenario {name!r}: one of {sorted(SCENARIOS)}")
    if slope_deg and not SCENARIOS[name].slope_deg:
        raise SystemExit(f"--slope-deg: scenario {name!r} has no slope")
    if rough_cm and not SCENARIOS[name].rough_m:
        raise SystemExit(f"--rough-cm: scenario {name!r} has no rough ground")
    cfg = closed_loop.ClosedLoopConfig(seconds=seconds, slope_deg=slope_deg, rough_cm=rough_cm)
    return closed_loop.scenario(cfg, name)


def main(argv: list[str] | None = None) -> dict:
    stride_jax.set_xla_flags()
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--robot", default="g1")
    ap.add_argument("--scenario", default="tilt")
    ap.add_argument("--slope-deg", type=float, default=0.0,
                    help="override the scenario's slope (0: keep), as the closed loop's flag")
    ap.add_argument("--rough-cm", type=float, default=0.0,
                    help="override the rough ground's bump height (cm; 0: keep), as the closed loop's flag")
    ap.add_argument("--models", required=True, help="NAME=RUN,... trained dynamics models")
    ap.add_argument("--policy", default="")
    ap.add_argument("--seconds", type=float, default=6.0)
    ap.add_argument("--split-s", default="2",
                    help="the phases: before and from this time (s); several, comma-separated "
                         "(e.g. a scenario's command changes, 1.5,3,4.5): the stretches between")
    ap.add_argument("--draws", type=int, default=8, help="residual draws per state")
    ap.add_argument("--nfe", type=int, default=0,
                    help="a generative residual's evaluations per sample (0: as trained)")
    ap.add_argument("--model-gravity", action="store_true",
                    help="a second row per model that takes a gravity direction, told the "
                         "sensed one (as the closed loop's --planning.model-gravity)")
    ap.add_argument("--govern", action="store_true",
                    help="the commands clipped to the policy's training range, as the closed "
                         "loop's --govern shows them to the controller")
    ap.add_argument("--prior", action="store_true",
                    help="rows of each structured model's Lagrangian prior alone (its residual "
                         "force left out)")
    ap.add_argument("--central", action="store_true",
                    help="rows of each stochastic model's central sample (the residual's latent "
                         "at its centre, z = 0: what the planner's --mppi.latents central steps "
                         "with), one per state")
    ap.add_argument("--out", required=True, help="path stem: writes OUT.md and OUT.json")
    a = ap.parse_args(argv)
    if a.draws < 1:
        raise SystemExit(f"--draws is {a.draws}: it must be >= 1")
    if a.nfe < 0:
        raise SystemExit(f"--nfe is {a.nfe}: it must be >= 1 (0: as trained)")
    try:
        splits = [float(x) for x in a.split_s.split(",") if x.strip()]
    except ValueError:
        raise SystemExit(f"--split-s {a.split_s!r}: expected times in s, comma-separated") from None
    phases(np.zeros(0), splits)  # checks them before the episode runs
    models = [tuple(m.split("=", 1)) for m in a.models.split(",") if m]
    if not models or any(len(m) != 2 for m in models):
        raise SystemExit(f"--models {a.models!r}: expected NAME=RUN,...")
    for name, run in models:
        if not (pathlib.Path(run) / "model.json").is_file():
            raise SystemExit(f"--models {name}={run}: no trained model there (model.json)")

    import jax

    from stride_jax.control.episode import learned_model, learned_step
    from stride_jax.dynamics import models as dyn_models
    from stride_jax.io import code_version, write_table
    from stride_jax.sim import model as sim_model

    sc = scenario(a.scenario, a.seconds, a.slope_deg, a.rough_cm)
    sm = sim_model.load(a.robot)
    policy = a.policy or f"results/policies/ppo_{a.robot}"
    t0 = time.time()
    t, q, qd, ctrl, q2, qd2, fallen, down = episode(sm, sc, policy, a.govern)
    if fallen.any():
        cut = int(np.argmax(fallen))
        print(f"the policy fell at {t[cut]:.2f} s: the states up to then are kept")
        t, q, qd, ctrl, q2, qd2, down = (x[:cut] for x in (t, q, qd, ctrl, q2, qd2, down))
    print(f"policy episode: {len(t)} control periods ({time.time() - t0:.0f} s)")
    dt, nu = sm.robot.ctrl_dt, sm.info.nu
    stretches = phases(t, splits)
    rows = []
    loaded = {run: learned_model(run, sm) for _, run in models}
    runs = [(name, run, False, False, False) for name, run in models]
    if a.model_gravity:
        runs += [(name, run, True, False, False) for name, run in models
                 if dyn_models.takes_gravity(loaded[run][0])]
    if a.prior:
        runs += [(name, run, told, True, False) for name, run, told, _, _ in list(runs)
                 if loaded[run][0].residual not in (None, "none")]
    if a.central:
        runs += [(name, run, told, False, True) for name, run, told, prior, _ in list(runs)
                 if loaded[run][0].stochastic and not prior]
    for base, run, told, prior, central in runs:
        name = (base + (" prior alone" if prior else "") + (" central" if central else "")
                + (" (told gravity)" if told else ""))
        t1 = time.time()
        step = learned_step(*(prior_alone(*loaded[run]) if prior else loaded[run]),
                            nfe=a.nfe or None)
        qd_pred = one_period(step, q, qd, ctrl, down if told else None,
                             1 if central else a.draws, central)
        err = qd2[:, None, :] - qd_pred  # true minus predicted velocity after one period
        acc_err = err[..., :3] / dt
        row = dict(model=name, run=run, told_gravity=told, prior_alone=prior, central=central)
        for label, sel in stretches.items():
            if sel.any():
                row[label] = phase_errors(acc_err[sel], err[sel], nu)
        rows.append(row)
        print(f"{name:>10}: " + "; ".join(
            f"{k}: bias {v['bias_norm']:.2f}, spread {v['spread_norm']:.2f} m/s^2, joints "
            f"{v['joint_vel_rmse']:.3f} rad/s" for k, v in row.items() if isinstance(v, dict))
            + f" ({time.time() - t1:.0f} s)", flush=True)
    command = "python " + " ".join(map(shlex.quote, [sys.argv[0], *(argv or sys.argv[1:])]))
    stem = pathlib.Path(a.out)
    stem.parent.mkdir(parents=True, exist_ok=True)
    env = dict(command=command, code=code_version(), backend=jax.default_backend(),
               scenario=sc.name, policy=policy, draws=a.draws, nfe=a.nfe or None, seconds=a.seconds,
               commands=sc.commands, govern=a.govern, splits=splits)
    lines = [f"# One-period model error along the policy's episode: {a.robot}, {sc.name}", "",
             f"Command: `{command}`", "",
             "Base linear acceleration error over one control period (true minus predicted, "
             "world axes x, y, z; m/s^2): the bias (its mean: what the planner's disturbance "
             "observer converges to) and the spread around it (RMS: what the observer cannot "
             f"absorb); joint-velocity RMSE after one period (rad/s), over every draw. "
             f"{a.draws} residual draws per state, the acceleration's error their mean per step"
             + (f"; {a.nfe} evaluations per residual sample" if a.nfe else "")
             + ("; rows `central`: the residual's central sample (z = 0), one per state"
                if a.central else "") + ".", "",
             "| model | phase | steps | bias x / y / z | spread x / y / z | joint vel RMSE |",
             "|---|---|---:|---|---|---:|"]
    for r in rows:
        for label in stretches:
            if label in r:
                v = r[label]
                lines.append(f"| {r['model']} | {label} | {v['steps']} | "
                             + " / ".join(f"{x:+.2f}" for x in v["bias"]) + " | "
                             + " / ".join(f"{x:.2f}" for x in v["spread"])
                             + f" | {v['joint_vel_rmse']:.3f} |")
    write_table(stem, dict(env=env, rows=rows), "\n".join(lines) + "\n")
    print(f"wrote {stem}.{{md,json}}")
    return dict(rows=rows)


if __name__ == "__main__":
    main()
