"""MPPI in closed loop on the MJX Go1 or G1: any dynamics model plans, the simulator acts.

Each control period (20 ms) the planner (:mod:`stride_jax.control.mppi`) sees the simulator's
state and the current command, plans through its model, and the first action is simulated in MJX
with the scenario's ground. Planner models:

* ``oracle``: the scenario's own MJX model (slope, friction, softness, terrain included);
* ``nominal``: MJX with the nominal flat ground the robot was designed and trained on;
* ``policy``: no planner -- the PPO policy acting alone (a baseline);
* ``NAME=RUN``: a trained dynamics model of the one interface (``stride_jax.dynamics.models.load``;
  STRIDE, DeLaN, ONN ...), e.g. ``stride=runs/go1/stride``.

The planner's view of the task (:mod:`stride_jax.control.planning`): its state is ``(q, command,
gait clock, latched gait)``, so one jitted planner follows command changes; its action is a
joint-target offset from home (with ``gait``, a residual on the Go1 gait reference plus the gait
parameters, optimised jointly); its cost is the environment's state reward terms, negated, plus a
tracking term and ``fall_cost`` per step fallen, or (``learned``) the learned reward and value. A
PPO run can add ``policy_samples`` candidates.

Scenarios (:mod:`stride_jax.control.scenarios`): velocity step 0 -> 2 m/s, sudden command
changes, a 20 degree slope, low friction, soft contacts, rough terrain. The gait study lives in
:mod:`stride_jax.jobs.gait_study`. Reported per (scenario, model): tracking RMSE of the
base-frame velocity (xy) and yaw rate while
upright, falls, and planning time per step.
"""

from __future__ import annotations

import dataclasses
import json
import pathlib
import time
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from mujoco import mjx

import stride_jax
from stride_jax import config
from stride_jax.control import envs, gait as gait_lib, mppi
# The configuration (re-exported); the planner's view of the task is in ``planning``.
from stride_jax.control.closed_loop_config import PRESETS, ClosedLoopConfig  # noqa: F401
from stride_jax.control.planning import (Planning, augment, make_planner, make_planning,
                                         mppi_config)
from stride_jax.control.scenarios import (SCENARIOS, WALK, Scenario, command_at,  # noqa: F401
                                          scenario_model, schedule)
from stride_jax.io import atomic_write_text, code_version
from stride_jax.sim import model as sim_model, rollout_mjx


# ---------------------------------------------------------------------------------------------
# One closed-loop episode.


class Trace(NamedTuple):
    """Per control step of a closed-loop episode (``[T, ...]``)."""

    t: jax.Array  # [T] s
    command: jax.Array  # [T, 3]
    v_base: jax.Array  # [T, 3] base-frame linear velocity (m/s)
    w_base: jax.Array  # [T, 3] base-frame angular velocity (rad/s)
    height: jax.Array  # [T] base height (m)
    fallen: jax.Array  # [T] bool
    contact: jax.Array  # [T, nfeet] bool, measured
    action: jax.Array  # [T, nu_plan] the applied planner action
    status: jax.Array  # [T] int32 the planner's mppi status (PLANNED, or why it fell back)
    cut: jax.Array  # [T] share of the planner's rollouts cut for predicted model error


def run_episode(sm: sim_model.SimModel, mx_sim: mjx.Model, slots, planning: Planning,
                planner: mppi.Planner | None, n_steps: int, starts: jax.Array,
                values: jax.Array, key: jax.Array, record: Callable | None = None
                ) -> Trace | tuple[Trace, object]:
    """A closed-loop episode of ``n_steps`` control steps from the home pose (heading +x) under
    the command :func:`schedule` ``(starts, values)``. ``planner=None`` lets ``planning.policy``
    act alone. Pure; jit it.

    ``record(q_aug, qd, u, info, q_aug_next, qd_next, down, key) -> pytree`` (with a planner)
    adds what it returns per step, stacked ``[T, ...]``: the episode then returns ``(trace,
    recorded)``. ``q_aug_next`` is the state reached under the step's command, ``down`` whether
    the robot was down before the step."""
    nu = sm.info.nu
    gait = len(planning.lo) > nu
    qpos0 = jnp.asarray(sm.info.qpos0).at[2].add(0.02)
    d0 = mjx.make_data(mx_sim).replace(qpos=qpos0, ctrl=jnp.asarray(sm.info.qpos0[7:]))
    dt = sm.robot.ctrl_dt
    horizon = 0
    if planner is not None:
        horizon = planner.init(key).plan.shape[0]
        ps0 = planner.init(key, jnp.broadcast_to(jnp.asarray(planning.nominal_u),
                                                 (horizon, len(planning.lo))))
    else:
        ps0 = ()
    if planner is None and planning.policy is None:
        raise ValueError("the policy-only model needs a PPO policy (--policy)")
    if record is not None and planner is None:
        raise ValueError("record needs a planner (it records the planner's candidates)")

    def body(carry, step):
        d, ps, clock, down = carry
        t = step * dt
        command = command_at(starts, values, t)
        q_aug = augment(d.qpos, command, clock)
        status, cut, info = jnp.zeros((), jnp.int32), jnp.zeros(()), None
        if planner is not None:
            u, ps, info = planner.step(ps, q_aug, d.qvel)
            status = info.status
            cut = jnp.mean(info.kept < horizon)
            if gait:  # gait parameters are per rollout: hold the chosen ones over the plan
                ps = ps._replace(plan=ps.plan.at[:, nu:].set(ps.plan[0, nu:]))
        else:
            u = planning.policy(q_aug, d.qvel)
        u = jnp.where(down, jnp.asarray(planning.nominal_u), u)  # fallen: stop planning effort
        d2 = envs.physics_step(mx_sim, sm.n_substeps, d, planning.ctrl(q_aug, u))
        freq = u[nu] if gait else planning.clock_hz
        clock = jnp.mod(clock + freq * dt, 1.0)
        finite = jnp.all(jnp.isfinite(d2.qpos)) & jnp.all(jnp.isfinite(d2.qvel))
        d2 = jax.tree.map(lambda a, b: jnp.where(finite, a, b), d2, d)  # freeze a diverged sim
        down2 = down | rollout_mjx.fallen(sm, d2.qpos) | ~finite
        v, w, _ = envs.base_signals(d2.qpos, d2.qvel)
        rec = Trace(t + dt, command, v, w, d2.qpos[2], down2, envs.foot_contact(sm, slots, d2),
                    u, status, cut)
        if record is not None:
            rec = (rec, record(q_aug, d.qvel, u, info, augment(d2.qpos, command, clock),
                               d2.qvel, down, jax.random.fold_in(key, step)))
        return (d2, ps, clock, down2), rec

    init = (d0, ps0, jnp.zeros(()), jnp.zeros((), bool))
    _, trace = jax.lax.scan(body, init, jnp.arange(n_steps))
    return trace


def metrics(trace: Trace, settle_s: float = 0.5) -> dict:
    """Tracking RMSE while upright (after ``settle_s`` from each command change), fall, speed."""
    tr = jax.tree.map(np.asarray, trace)
    up = ~tr.fallen
    changed = np.r_[True, np.any(np.diff(tr.command, axis=0) != 0, axis=1)]
    since = np.zeros(len(tr.t))
    last = 0.0
    for i, (t, c) in enumerate(zip(tr.t, changed)):
        last = t if c else last
        since[i] = t - last
    use = up & (since >= settle_s)
    v_err = np.linalg.norm(tr.v_base[:, :2] - tr.command[:, :2], axis=1)
    w_err = np.abs(tr.w_base[:, 2] - tr.command[:, 2])
    rmse = lambda e: float(np.sqrt(np.mean(e[use] ** 2))) if use.any() else float("nan")
    fell = bool(tr.fallen.any())
    out = dict(vel_rmse=rmse(v_err), yaw_rmse=rmse(w_err), fell=fell,
               fall_s=float(tr.t[np.argmax(tr.fallen)]) if fell else None,
               mean_vx=float(tr.v_base[up, 0].mean()) if up.any() else float("nan"),
               upright_s=float(up.sum() * (tr.t[1] - tr.t[0]) if len(tr.t) > 1 else 0.0),
               fallbacks=int((tr.status != mppi.PLANNED).sum()),
               cut_share=float(tr.cut.mean()))
    if up.sum() >= 10 and tr.contact.shape[1] == 4:  # the quadruped gait the feet showed
        out["contact_gait"], out["contact_gait_score"] = gait_lib.classify_contacts(
            tr.contact[up])
    n_joint = tr.contact.shape[1] * 3
    if tr.contact.shape[1] == 4 and tr.action.shape[1] > n_joint and up.any():  # planned gait
        g = np.median(tr.action[up, n_joint:], axis=0)
        out["plan_freq"], out["plan_duty"] = float(g[0]), float(g[1])
        out["plan_gait"], out["plan_gait_dist"] = gait_lib.classify(g[2:])
    return out


# ---------------------------------------------------------------------------------------------
# Models, the driver, the table and the plots.


def mjx_step_fn(sm: sim_model.SimModel, mx: mjx.Model) -> Callable:
    """``step(q, qd, ctrl, key) -> (q', qd')`` of an MJX model (the oracle's dynamics)."""
    return envs.mjx_step_fn(sm.n_substeps, mx)


def learned_step_fn(run: str, sm: sim_model.SimModel, kernel: str = "xla") -> Callable:
    """``step(q, qd, ctrl, key)`` of a trained dynamics model (``stride train`` run folder),
    its networks run as ``kernel`` (``StructuredConfig.kernel``)."""
    from stride_jax.dynamics import models
    model, params = models.load(run, kernel=kernel)
    q0 = jnp.asarray(sm.info.qpos0)
    try:  # shape check at the boundary: the run must model this robot
        jax.eval_shape(lambda: model.step(params, q0, jnp.zeros(sm.mj.nv),
                                          q0[7:], jax.random.key(0)))
    except ValueError as e:
        raise ValueError(f"{run} does not model robot {sm.robot.name}: {e}") from e
    return lambda q, qd, ctrl, key: model.step(params, q, qd, ctrl, key)


def _parse_models(spec: str) -> list[tuple[str, str]]:
    out = []
    for item in [s for s in spec.split(",") if s]:
        name, _, run = item.partition("=")
        if not run and name not in ("oracle", "nominal", "policy"):
            raise ValueError(f"unknown model {item!r}: use oracle, nominal, policy or NAME=RUN")
        out.append((name, run))
    return out


def run(cfg: ClosedLoopConfig, command: str = "", log=print) -> list[dict]:
    """Every (scenario, model) pair of ``cfg``; writes ``closed_loop.json``/``.md``, traces and
    plots to ``cfg.out`` after each pair, and skips pairs already there (resumable)."""
    from stride_jax.control import learned as learned_lib, ppo
    from stride_jax.dynamics import fused

    fused.kernel_dtype(cfg.kernel)  # a clear error for an unknown choice, before any work
    sm = sim_model.load(cfg.robot)
    unknown = [s for s in cfg.scenarios.split(",") if s and s not in SCENARIOS]
    if unknown:
        raise ValueError(f"unknown scenarios {unknown}; known: {', '.join(SCENARIOS)}")
    models = _parse_models(cfg.models)
    ppo_policy, env_cfg = None, envs.config(cfg.robot)
    if cfg.policy:
        ppo_policy, _, env_cfg = ppo.load_policy(cfg.policy)
        if env_cfg.robot != cfg.robot:
            raise ValueError(f"the policy {cfg.policy} drives {env_cfg.robot}, not {cfg.robot}")
    learned_params = learned_lib.load(cfg.learned) if cfg.learned else None
    error_params = None
    if cfg.error_model:
        from stride_jax.control import planner_value
        error_params = planner_value.load_error_model(cfg.error_model)
    out = pathlib.Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "closed_loop.json"
    rows = json.loads(path.read_text())["rows"] if path.is_file() else []
    done = {(r["scenario"], r["model"]) for r in rows}
    mx_nominal = mjx.put_model(sm.mj)
    learned_steps = {name: learned_step_fn(run_dir, sm, cfg.kernel) for name, run_dir in models
                     if run_dir}
    if any(name == "policy" for name, _ in models) and ppo_policy is None:
        raise ValueError("model 'policy' needs --policy RUN")
    compiled = {}  # one executable per (model, episode length, model structures)

    def episode_fn(name, n_steps, slots):
        def episode(mx_sim, mx_plan, starts, values, key):
            step_fn = learned_steps.get(name) or mjx_step_fn(sm, mx_plan)
            planning = make_planning(cfg, env_cfg, sm, step_fn, ppo_policy, learned_params,
                                     error_params=error_params if name in learned_steps
                                     else None)  # the simulator has no model error
            planner = None
            if name != "policy":
                with jax.ensure_compile_time_eval():  # mppi.make checks its bounds eagerly
                    planner = make_planner(planning, mppi_config(cfg, planning))
            return run_episode(sm, mx_sim, slots, planning, planner, n_steps, starts, values, key)
        return jax.jit(episode)

    for sc_name in [s for s in cfg.scenarios.split(",") if s]:
        sc = SCENARIOS[sc_name]
        if cfg.seconds:
            sc = dataclasses.replace(sc, seconds=cfg.seconds)
        n_steps = max(1, int(round(sc.seconds / sm.robot.ctrl_dt)))
        mx_sim = mjx.put_model(scenario_model(sm, sc, cfg.seed))
        slots = envs.contact_slots(mx_sim)
        starts, values = schedule(sc)
        for name, run_dir in models:
            if (sc.name, name) in done:
                continue
            mx_plan = mx_sim if name == "oracle" else mx_nominal
            args = (mx_sim, mx_plan, jnp.asarray(starts), jnp.asarray(values),
                    jax.random.key(cfg.seed))
            sig = (name, n_steps, tuple(slots[0]), jax.tree.structure(args[:2]))
            t0 = time.perf_counter()
            if sig not in compiled:
                compiled[sig] = episode_fn(name, n_steps, slots).lower(*args).compile()
            compile_s = time.perf_counter() - t0
            t0 = time.perf_counter()
            trace = jax.block_until_ready(compiled[sig](*args))
            run_s = time.perf_counter() - t0
            planned = name != "policy"
            row = dict(scenario=sc.name, model=name, run=run_dir or None,
                       **metrics(trace, cfg.settle_s),
                       ms_per_step=1e3 * run_s / n_steps, compile_s=compile_s, steps=n_steps,
                       K=cfg.mppi.samples if planned else None,
                       H=cfg.mppi.horizon if planned else None)
            rows.append(row)
            np.savez_compressed(out / f"trace_{sc.name}_{name}.npz",
                                **{k: np.asarray(v) for k, v in trace._asdict().items()})
            write(rows, cfg, command, out)
            log(f"{sc.name:>12} {name:>8}: vel RMSE {row['vel_rmse']:.3f} m/s, yaw RMSE "
                f"{row['yaw_rmse']:.3f} rad/s, fell {row['fell']}, {row['ms_per_step']:.1f} ms/step"
                f" (compile {compile_s:.0f} s)")
    plot(out, rows)
    return rows


def write(rows: list[dict], cfg: ClosedLoopConfig, command: str, out: pathlib.Path) -> None:
    env = dict(command=command, backend=jax.default_backend(), device=jax.devices()[0].device_kind,
               jax=jax.__version__, code=code_version(), config=dataclasses.asdict(cfg))
    atomic_write_text(out / "closed_loop.json", json.dumps(dict(env=env, rows=rows), indent=1))
    fmt = lambda x, f="{:.3f}": "-" if x is None or (isinstance(x, float) and np.isnan(x)) else (
        f.format(x))
    robot = {"go1": "Go1", "g1": "G1"}.get(cfg.robot, cfg.robot)
    lines = [f"# Closed-loop MPPI on the MJX {robot}", "", f"Command: `{command}`", "",
             f"Device: {env['device']} ({env['backend']}), jax {env['jax']}. MPPI K={cfg.mppi.samples}, "
             f"H={cfg.mppi.horizon}, {cfg.mppi.iterations} iteration(s); cost: "
             f"{'learned reward/value ' + cfg.learned if cfg.learned else 'analytic reward terms'}"
             f"{', gait parameters planned' if cfg.gait else ''}"
             f"{', PPO candidates from ' + cfg.policy if cfg.policy and cfg.mppi.policy_samples else ''}"
             ". Tracking RMSE of the base-frame velocity (xy) and yaw rate while upright, "
             f"{cfg.settle_s} s after each command change.", "",
             "Gait: the named pattern the measured foot contacts fit best (score: in-phase minus "
             "anti-phase contact correlation); with planned gaits, the median planned "
             "parameters too.", "",
             "| scenario | model | vel RMSE (m/s) | yaw RMSE (rad/s) | mean vx (m/s) | fell | "
             "fall at (s) | contact gait (score) | planned gait | ms/step |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        planned = (f"{r['plan_gait']} ({r['plan_freq']:.1f} Hz, duty {r['plan_duty']:.2f})"
                   if "plan_gait" in r else "-")
        contact = (f"{r['contact_gait']} ({r['contact_gait_score']:.2f})"
                   if "contact_gait" in r else "-")
        lines.append(f"| {r['scenario']} | {r['model']} | {fmt(r['vel_rmse'])} | "
                     f"{fmt(r['yaw_rmse'])} | {fmt(r['mean_vx'], '{:.2f}')} | "
                     f"{'yes' if r['fell'] else 'no'} | {fmt(r['fall_s'], '{:.2f}')} | "
                     f"{contact} | {planned} | {r['ms_per_step']:.1f} |")
    atomic_write_text(out / "closed_loop.md", "\n".join(lines) + "\n")


def plot(out: pathlib.Path, rows: list[dict]) -> list[pathlib.Path]:
    """One figure per scenario: forward velocity and yaw rate against the command, per model."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    for sc in dict.fromkeys(r["scenario"] for r in rows):
        fig, ax = plt.subplots(1, 3, figsize=(14, 3.6))
        cmd_drawn = False
        for r in [r for r in rows if r["scenario"] == sc]:
            f = out / f"trace_{sc}_{r['model']}.npz"
            if not f.is_file():
                continue
            tr = np.load(f)
            if not cmd_drawn:
                for i, label in enumerate(("vx", "vy", "yaw rate")):
                    ax[i].plot(tr["t"], tr["command"][:, i], "k--", lw=1, label="command")
                cmd_drawn = True
            up = ~tr["fallen"]
            for i, series in enumerate((tr["v_base"][:, 0], tr["v_base"][:, 1],
                                        tr["w_base"][:, 2])):
                ax[i].plot(tr["t"][up], series[up], lw=1, label=r["model"])
        for i, label in enumerate(("vx (m/s)", "vy (m/s)", "yaw rate (rad/s)")):
            ax[i].set(xlabel="t (s)", ylabel=label)
        ax[0].legend(fontsize=7)
        fig.suptitle(f"closed loop, scenario {sc} (lines stop at a fall)")
        fig.tight_layout()
        path = out / f"closed_loop_{sc}.png"
        fig.savefig(path, dpi=90)
        plt.close(fig)
        paths.append(path)
    return paths


def main(argv: list[str] | None = None) -> None:
    config.config_main("python -m stride_jax.control.closed_loop", ClosedLoopConfig, PRESETS, run,
                      argv, __doc__.split("\n")[0])


if __name__ == "__main__":
    stride_jax.set_xla_flags()  # before JAX starts: small CPUs deadlock without
    main()
