"""One closed-loop episode: a planner (or a policy) acting on an MJX simulation, and what it
measured.

Each control period (20 ms) the planner (:mod:`stride_jax.control.mppi`) sees the simulator's
state and the current command, plans through its model (:mod:`stride_jax.control.planning`: the
planner's view of the task), and the first action is simulated in MJX with the scenario's ground
(:mod:`stride_jax.control.scenarios`). The planner's model is any ``step(q, qd, ctrl, key)``:
:func:`mjx_step_fn` (an MJX model: the oracle or the nominal ground) or :func:`learned_step_fn`
(a trained dynamics model of the one interface, ``stride_jax.dynamics.load``).

The job that runs every (scenario, model) pair and writes the table and plots is
``stride closed-loop`` (``stride_jax.jobs.closed_loop``).
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from mujoco import mjx

from stride_jax.control import envs, gait as gait_lib, mppi
from stride_jax.control.planning import (N_AUG, N_DIST, Planning, PlanningConfig, augment,
                                         integral_command, integrate_overspeed,
                                         integrate_velocity_error, make_planning, observe_step,
                                         overspeed_command, split, update_disturbance)
from stride_jax.control.scenarios import (Scenario, command_at, governed, gravity_at,
                                          push_schedule, scenario_model, schedule, tilt_schedule,
                                          world_at)
from stride_jax.sim import model as sim_model, rollout_mjx, sensors as sensors_lib


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
    disturbance: jax.Array  # [T, 6] the observer's base-acceleration estimate after the step
    alarm: jax.Array  # [T] bool: the planner drew its recovery candidates (``alarm_noise_std``)


def sensed_gravity(mx: mjx.Model, t: jax.Array, tilt: jax.Array | None = None) -> jax.Array:
    """The gravity direction ``[3]`` (world, unit) an IMU senses at time ``t`` (s) in the
    scenario's model ``mx``: its own gravity, tilted by a :func:`tilt_schedule` where given."""
    g = mx.opt.gravity if tilt is None else gravity_at(tilt, t, mx.opt.gravity)
    return g / jnp.maximum(jnp.linalg.norm(g), 1e-9)


class World(NamedTuple):
    """A scenario made ready for :func:`run_episode`: ``sm`` the robot on the scenario's model
    (its geom ids: the feet's contact flags), ``mx`` that model in MJX, ``slots`` its feet's
    contact slots, ``n_steps`` control periods, and the command, push and tilt schedules as
    arrays (so that scenarios share one compiled episode)."""

    sm: sim_model.SimModel
    mx: mjx.Model
    slots: tuple
    n_steps: int
    starts: jax.Array
    values: jax.Array
    pushes: jax.Array
    tilt: jax.Array


def scenario_world(sm: sim_model.SimModel, sc: Scenario, seed: int = 0) -> World:
    """Scenario ``sc``'s :class:`World` for robot ``sm`` (``seed``: its rough ground's draw)."""
    m = scenario_model(sm, sc, seed)
    mx = mjx.put_model(m)
    starts, values = schedule(sc)
    return World(sim_model.on_model(sm, m), mx, envs.contact_slots(mx),
                 max(1, int(round(sc.seconds / sm.robot.ctrl_dt))), jnp.asarray(starts),
                 jnp.asarray(values), jnp.asarray(push_schedule(sc, float(sm.mj.body_mass.sum()))),
                 jnp.asarray(tilt_schedule(sc)))


def run_episode(sm: sim_model.SimModel, mx_sim: mjx.Model, slots, planning: Planning,
                planner: mppi.Planner | None, n_steps: int, starts: jax.Array,
                values: jax.Array, key: jax.Array, record: Callable | None = None,
                pushes: jax.Array | None = None,
                limits: tuple[jax.Array, jax.Array] | None = None,
                tilt: jax.Array | None = None, progress: Callable | None = None,
                progress_every: int = 50, sense_gravity: bool = True,
                sensors: sensors_lib.SensorNoise | None = None, record_every: int = 1
                ) -> Trace | tuple[Trace, object]:
    """A closed-loop episode of ``n_steps`` control steps from the home pose (heading +x) under
    the command :func:`schedule` ``(starts, values)``. ``planner=None`` lets ``planning.policy``
    act alone. Pure; jit it.

    ``record(q_aug, qd, u, info, q_aug_next, qd_next, down, key) -> pytree`` (with a planner)
    adds what it returns per step, stacked ``[T, ...]``: the episode then returns ``(trace,
    recorded)``; with ``record_every`` N > 1 it runs at every N-th control step only (from the
    first), its outputs zero at the others (a costly record, such as replaying the candidates in
    the simulator, then costs 1/N). ``q_aug_next`` is the state reached under the step's
    command (with the gravity sensed at its time), ``down`` whether the robot was down before
    the step. ``pushes`` (:func:`stride_jax.control.scenarios.push_schedule`) applies
    horizontal forces to the base body (unknown to the planner's model).
    ``limits = (lo [3], hi [3])`` is a command governor: the controller (policy and planner) sees
    the command clipped to them, the trace keeps the command asked for, so the tracking metrics
    count what the clipping gives up. ``tilt`` (:func:`stride_jax.control.scenarios.
    tilt_schedule`) builds the slope up over the episode's first seconds: the simulation's gravity
    at each step is :func:`stride_jax.control.scenarios.gravity_at` (``mx_sim``'s own where the
    schedule does not build up); the planner's model is told it only under ``planning``'s
    ``model_gravity`` (``PlanningConfig.model_gravity``). ``progress(steps_done)`` is
    called on the host every ``progress_every`` control steps (``jax.debug.callback``; long
    episodes, e.g. planning through MJX, otherwise run silent for minutes).

    With ``planning.observer_gain`` > 0 (and a planner) a disturbance observer runs beside the
    planner: after each real step the planner's model predicts the same step from the same state
    and action under the current estimate ``d``, and ``d += gain * (qd_real - qd_pred)[:6] / dt``
    (bounded by ``planning.observer_limit``, held while fallen or after a non-finite step). The
    planner sees ``d`` in its state and adds it to every rollout step
    (:func:`stride_jax.control.planning.apply_disturbance`): integral action, so a persistent
    model error (a slope, a payload) stops biasing the plan. With ``planning.velocity_filter``
    the controller acts on the base's measured linear velocity blended with that prediction
    (the last period's, for this one): the learned model as a filter of a noisy estimate.

    ``sense_gravity``: the policy and the planner observe the simulation's gravity direction
    (:func:`sensed_gravity`), as an IMU on a real slope senses the slope; ``False``: world down,
    as every run before session 46 did, which hides an emulated slope from them (the floor stays
    level while gravity tilts).

    ``sensors``: the controller sees the state through a real robot's sensors and state
    estimator (:func:`stride_jax.sim.sensors.measure`, a fresh draw each period): the policy, the
    planner, the disturbance observer (the state before and after each step as measured) and the
    integral action (the measured base velocity) read it; the world, the trace and the fall check
    keep the true state. None: the exact state, as every run before session 81."""
    init, body = _episode(sm, mx_sim, slots, planning, planner, starts, values, key, record,
                          pushes, limits, tilt, progress, progress_every, sense_gravity, sensors,
                          record_every)
    _, trace = jax.lax.scan(body, init, jnp.arange(n_steps))
    return trace


def start_episode(sm: sim_model.SimModel, mx_sim: mjx.Model, planning: Planning,
                  planner: mppi.Planner | None, key: jax.Array):
    """The state a closed-loop episode starts from (the simulation at the home pose, the
    planner's warm start, the task clock, fallen, the observer's estimate): what
    :func:`continue_episode` takes and returns. Pure; jit it."""
    return _episode(sm, mx_sim, (), planning, planner, None, None, key)[0]


def continue_episode(sm: sim_model.SimModel, mx_sim: mjx.Model, slots, planning: Planning,
                     planner: mppi.Planner | None, carry, first_step: jax.Array, n_steps: int,
                     starts: jax.Array, values: jax.Array, key: jax.Array,
                     pushes: jax.Array | None = None,
                     limits: tuple[jax.Array, jax.Array] | None = None,
                     tilt: jax.Array | None = None, progress: Callable | None = None,
                     progress_every: int = 50, sense_gravity: bool = True,
                     sensors: sensors_lib.SensorNoise | None = None):
    """``n_steps`` control steps of :func:`run_episode`'s episode from ``carry`` (of
    :func:`start_episode` or of an earlier call) at control step ``first_step`` (traced: one
    program serves every chunk): ``(carry, trace)``. Chunks run one after another give
    :func:`run_episode`'s trace, so a long episode can be saved between them and resumed
    (``stride closed-loop --chunk-s``). Pure; jit it."""
    _, body = _episode(sm, mx_sim, slots, planning, planner, starts, values, key, None, pushes,
                       limits, tilt, progress, progress_every, sense_gravity, sensors)
    return jax.lax.scan(body, carry, first_step + jnp.arange(n_steps))


def controller_period(sm: sim_model.SimModel, mx_sim: mjx.Model, planning: Planning,
                      planner: mppi.Planner | None, carry, key: jax.Array):
    """The controller's own computation in one control period from an episode's state ``carry``
    (:func:`start_episode`'s), under a standing command: what a robot's computer runs each
    period, without the simulated world's step: ``(u, planner state, observer estimate)``. Time
    it to learn whether a planner keeps up with the control rate (``stride closed-loop``'s
    ``controller_ms``). It is the planner's step and, with ``planning.observer_gain``, the
    observer's prediction of the step just taken (the real step taken as that prediction's
    input here: the same work); with ``planning.latency_s``, a replanning period's work (the
    compensation's prediction, the plan, the feedback's references, the period's action); with
    no planner, the policy. Pure; jit it."""
    d, ps, clock, _, dist, *rest = carry
    q_aug = augment(d.qpos, jnp.zeros(3, d.qpos.dtype), clock, disturbance=dist,
                    gravity=sensed_gravity(mx_sim, jnp.zeros(())))
    late = rest[-1] if planner is not None and planning.latency_steps else None
    u, ps, _, _, _ = _control(sm, planning, planner, ps, late, jnp.zeros((), jnp.int32), q_aug,
                              d.qvel)
    if planner is not None and planning.observer_gain > 0:
        central = planner.latents == "central"
        dist = update_disturbance(planning, q_aug, d.qvel, u, d.qvel, sm.robot.ctrl_dt,
                                  None if central else key)
    return u, ps, dist


def _control(sm, planning: Planning, planner: mppi.Planner | None, ps, late, step, q_aug, qd):
    """The controller's action in one control period, as :func:`run_episode` and
    :func:`controller_period` both run it: ``(u, ps, late, (status, cut, alarm), info)`` (the
    planner's ``info`` where it planned this period on time, else None); the policy alone where
    there is no planner, a late planner (:func:`_late_plan`) where ``late`` is given."""
    quiet = (jnp.zeros((), jnp.int32), jnp.zeros(()), jnp.zeros((), bool))
    if planner is None:
        return planning.policy(q_aug, qd), ps, late, quiet, None
    nu = sm.info.nu
    gait = len(planning.lo) > nu
    if late is not None:
        u, ps, late = _late_plan(planning, planner, late, ps, step, planning.latency_steps,
                                 q_aug, qd, gait, nu, sm.robot.ctrl_dt)
        return u, ps, late, late[1], None
    u, ps, info = planner.step(ps, q_aug, qd)
    cut = jnp.mean(info.kept < ps.plan.shape[0])
    if gait:  # gait parameters are per rollout: hold the chosen ones over the plan
        ps = ps._replace(plan=ps.plan.at[:, nu:].set(ps.plan[0, nu:]))
    return u, ps, late, (info.status, cut, info.alarm), info


def _episode(sm, mx_sim, slots, planning, planner, starts, values, key, record=None, pushes=None,
             limits=None, tilt=None, progress=None, progress_every=50, sense_gravity=True,
             sensors=None, record_every=1):
    """``(init, body)`` of :func:`run_episode`'s scan over control steps."""
    nu = sm.info.nu
    gait = len(planning.lo) > nu
    qpos0 = jnp.asarray(sm.info.qpos0).at[2].add(0.02)
    d0 = mjx.make_data(mx_sim).replace(qpos=qpos0, ctrl=jnp.asarray(sm.info.qpos0[7:]))
    dt = sm.robot.ctrl_dt
    base = int(sm.mj.jnt_bodyid[0])  # the floating base's body
    horizon = 0
    if planner is not None:
        horizon = jax.eval_shape(planner.init, key).plan.shape[0]  # its shape alone, no work
        ps0 = planner.init(key, jnp.broadcast_to(jnp.asarray(planning.nominal_u),
                                                 (horizon, len(planning.lo))))
    else:
        ps0 = ()
    if planner is None and planning.policy is None:
        raise ValueError("the policy-only model needs a PPO policy (--policy)")
    if record is not None and planner is None:
        raise ValueError("record needs a planner (it records the planner's candidates)")
    if not (isinstance(record_every, int) and record_every >= 1):
        raise ValueError(f"record_every={record_every!r}: a whole number of control steps >= 1")

    observe = planner is not None and planning.observer_gain > 0
    obs_key = jax.random.fold_in(key, 0x0B5E)  # the observer's own draws
    central = planner is not None and planner.latents == "central"  # it predicts as the planner

    integrate = planner is not None and planning.velocity_integral > 0
    guard = planning.overspeed_gain > 0  # whichever controller acts, the policy alone too
    filtered = observe and planning.velocity_filter > 0
    lat = planning.latency_steps if planner is not None else 0
    if filtered and not sm.robot.floating_base:
        raise ValueError("velocity_filter blends the base's linear velocity: "
                         f"{sm.robot.name} has no floating base")
    if lat and record is not None:
        raise ValueError(f"record reads the planner's step as it acts; with latency_steps={lat} "
                         "its plans act later: record needs a planner without latency")
    if sensors is not None and record is not None:
        raise ValueError("record pairs the planner's candidates with the true states: it needs "
                         "the exact state (sensors=None)")
    sense_key = jax.random.fold_in(key, 0x5E45)  # the sensors' own draws

    def seen(d_, step):
        """``(qpos, qvel)`` of ``d_`` at period ``step`` as the controller sees them."""
        if sensors is None:
            return d_.qpos, d_.qvel
        return sensors_lib.measure(sensors, d_.qpos, d_.qvel, jax.random.fold_in(sense_key, step),
                                   sm.robot.floating_base)

    def body(carry, step):
        d, ps, clock, down, dist, *rest = carry  # rest: the integral's, guard's, filter's,
        track = rest[:1] if integrate else []     # latency's
        over = rest[len(track)] if guard else None  # the overspeed guard's integral
        pred = rest[len(track) + guard] if filtered else None  # the observer's prediction
        late = rest[-1] if lat else None
        t = step * dt
        command = command_at(starts, values, t)
        command_seen = command if limits is None else jnp.clip(command, limits[0], limits[1])
        asked = command_seen  # what the controller is asked (governed), before the integral
        if integrate:  # integral action: the planner tracks the command moved against the error
            (integral, since, prev), = track
            command_seen = integral_command(planning, command_seen, integral)
        if guard:  # the overspeed guard: the speed asked lowered by the integrated overspeed
            command_seen = overspeed_command(planning, command_seen, over)
        up = sensed_gravity(mx_sim, t, tilt) if sense_gravity else None
        qpos_m, qvel_m = seen(d, step)
        if filtered:  # the model's prediction blended into the base's measured velocity
            blend = qvel_m[:3] + planning.velocity_filter * (pred - qvel_m[:3])
            qvel_m = qvel_m.at[:3].set(jnp.where(jnp.all(jnp.isfinite(blend)), blend,
                                                 qvel_m[:3]))
        q_aug = augment(qpos_m, command_seen, clock, disturbance=dist, gravity=up)
        u, ps, late, (status, cut, alarm), info = _control(sm, planning, planner, ps, late,
                                                            step, q_aug, qvel_m)
        u = jnp.where(down, jnp.asarray(planning.nominal_u), u)  # fallen: stop planning effort
        mx_t, d = world_at(mx_sim, d, base, t, pushes, tilt)
        d2 = envs.physics_step(mx_t, sm.n_substeps, d, planning.ctrl(q_aug, u))
        freq = u[nu] if gait else planning.clock_hz
        clock = jnp.mod(clock + freq * dt, 1.0)
        finite = jnp.all(jnp.isfinite(d2.qpos)) & jnp.all(jnp.isfinite(d2.qvel))
        d2 = jax.tree.map(lambda a, b: jnp.where(finite, a, b), d2, d)  # freeze a diverged sim
        down2 = down | rollout_mjx.fallen(sm, d2.qpos) | ~finite
        if observe or integrate or guard:  # the next period's reading, as that period draws it
            qpos2_m, qvel2_m = seen(d2, step + 1)
        if observe:  # the planner's model predicts the step just taken; integrate its error
            new, qd_pred = observe_step(planning, q_aug, qvel_m, u, qvel2_m, dt,
                                        None if central else jax.random.fold_in(obs_key, step))
            dist = jnp.where(finite & ~down2, new, dist)
            if filtered:  # held where the world or the robot went astray: the measurement
                pred = jnp.where(finite & ~down2, qd_pred[:3], jnp.nan)
        v, w, _ = envs.base_signals(d2.qpos, d2.qvel)
        if integrate or guard:  # the base's velocity as the controller reads it
            v_m = v if sensors is None else envs.base_signals(qpos2_m, qvel2_m)[0]
        if integrate:
            track = [(*integrate_velocity_error(planning, integral, since, asked, prev, v_m, dt),
                      asked)]
        if guard:  # against the command asked (governed), the integral's shift aside
            over = jnp.where(down2, over, integrate_overspeed(planning, over, asked, v_m, dt))
        rec = Trace(t + dt, command, v, w, d2.qpos[2], down2, envs.foot_contact(sm, slots, d2),
                    u, status, cut, dist, alarm)
        if record is not None:
            up2 = sensed_gravity(mx_sim, t + dt, tilt) if sense_gravity else None
            args = (q_aug, d.qvel, u, info,
                    augment(d2.qpos, command_seen, clock, disturbance=dist, gravity=up2),
                    d2.qvel, down, jax.random.fold_in(key, step))
            if record_every == 1:
                rec = (rec, record(*args))
            else:  # (the step is the scan's, never batched: a real branch under vmap)
                blank = lambda a: jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype),
                                               jax.eval_shape(lambda a: record(*a), a))
                rec = (rec, jax.lax.cond(step % record_every == 0, lambda a: record(*a), blank,
                                         args))
        if progress is not None:
            jax.lax.cond((step + 1) % progress_every == 0,
                         lambda s: jax.debug.callback(progress, s), lambda s: None, step + 1)
        return (d2, ps, clock, down2, dist, *track, *([over] if guard else []),
                *([pred] if filtered else []), *([late] if lat else [])), rec

    init = (d0, ps0, jnp.zeros(()), jnp.zeros((), bool), jnp.zeros(N_DIST, d0.qpos.dtype))
    if integrate:  # the integrated error, the time since the last command change, the last
        # command (the first period counts as a change); absent when off: the carry (and a
        # chunked run's saved state) as before
        init += ((jnp.zeros(2, d0.qpos.dtype), jnp.zeros((), d0.qpos.dtype),
                  jnp.full(3, jnp.nan, d0.qpos.dtype)),)
    if guard:  # the overspeed guard's integral (absent when off: the carry as before)
        init += (jnp.zeros((), d0.qpos.dtype),)
    if filtered:  # the observer's prediction of the next period's base linear velocity (none
        # yet: the first period acts on its measurement)
        init += (jnp.full(3, jnp.nan, d0.qpos.dtype),)
    if lat:  # the plan in force and the (status, cut, alarm) of it and of the plan in flight
        # (in the planner's state); at the start both are the planner's initial plan; with the
        # policy's feedback, the policy at the states predicted along each (none yet: NaN, the
        # plan as planned)
        quiet = (jnp.asarray(mppi.PLANNED, jnp.int32), jnp.zeros(()), jnp.zeros((), bool))
        refs = ((jnp.full((lat, len(planning.lo)), jnp.nan),) * 2
                if planning.latency_feedback else ())
        init += ((ps0.plan, quiet, quiet, *refs),)
    return init, body


def _late_plan(planning: Planning, planner: mppi.Planner, late, ps, step, lat: int, q_aug, qd,
               gait: bool, nu: int, dt: float):
    """One control period of a planner whose computation takes ``lat`` periods
    (``PlanningConfig.latency_s``): ``(u, ps, late)``. ``late = (active, in_force, in_flight)``:
    the plan in force (its first action applied at the last replanning period) and the
    ``(status, cut, alarm)`` of it and of the plan in flight, which is ``ps.plan``. Every ``lat``
    periods the plan in flight takes force and the next is computed: from the state the model
    predicts ``lat`` periods on under the actions in force (``planning.latency_compensation``)
    or from the state now, warm-started from the plan in force shifted to when it will apply.
    In between the plan in force plays on (its last action held where the computation outlasts
    the plan's horizon); where the trust gate handed the robot to the policy (``DISTRUSTED``)
    the policy acts each period on the state now. With ``planning.latency_feedback`` ``late``
    also holds the policy's actions at the states predicted along the plan in force and the
    plan in flight over their windows, and each period applies the plan's action plus the
    policy's at the state now minus the policy's at the state predicted for it."""
    active, in_force, in_flight, *refs = late  # refs: the policy at the plans' predictions
    nq = q_aug.shape[-1] - N_AUG
    handed = lambda force: force[0] == mppi.DISTRUSTED
    H = active.shape[0]
    at = lambda plan, k: plan[jnp.minimum(k, H - 1)]  # past its end a plan holds its last action

    def act(force, plan_u, ref, q_a, qd_):
        """The action of a plan in force at ``(q_a, qd_)``: its own, the policy's where it was
        handed over, and with the policy's feedback ``plan_u + policy(now) - ref`` (``ref``:
        the policy at the state predicted for this period; the plan's own where not finite)."""
        if planning.policy is None:
            return plan_u
        pol = planning.policy(q_a, qd_)  # once: the hand-over and the feedback both read it
        u_pol = jnp.clip(pol, planning.lo, planning.hi)
        u = jnp.where(handed(force) & jnp.all(jnp.isfinite(u_pol)), u_pol, plan_u)
        if ref is None:
            return u
        fed = jnp.clip(u + pol - ref, planning.lo, planning.hi)
        return jnp.where(jnp.all(jnp.isfinite(fed)) & ~handed(force), fed, u)

    def along(q_a, qd_, action):
        """The model's prediction (a stochastic residual's central sample) over ``lat`` periods
        from ``(q_a, qd_)`` under ``action(k, q_aug, qd)``: the states before each period and
        the state after the last, as the planner sees them (the command, observer estimate and
        gravity of now, the clock run on)."""
        now = split(q_a, nq)
        q, clk, states = now.q, now.clock, []
        aug = lambda q, clk: augment(q, now.command, clk, disturbance=now.disturbance,
                                     gravity=now.gravity)
        for k in range(lat):
            a = aug(q, clk)
            u_k = action(k, a, qd_)
            states.append((a, qd_))
            q2, qd_ = planning.dynamics(a, qd_, u_k, None)
            q = split(q2, nq).q
            clk = jnp.mod(clk + (u_k[nu] if gait else planning.clock_hz) * dt, 1.0)
        return states, aug(q, clk), qd_

    def replan(ps):
        active, force = ps.plan, in_flight  # the plan in flight takes force now
        start_q, start_qd = q_aug, qd
        if planning.latency_compensation:  # under the actions in force until it applies
            _, pred, qd_p = along(q_aug, qd, lambda k, a, v: act(
                force, at(active, k), refs[1][k] if refs else None, a, v))
            ok = jnp.all(jnp.isfinite(pred)) & jnp.all(jnp.isfinite(qd_p))
            start_q, start_qd = jnp.where(ok, pred, q_aug), jnp.where(ok, qd_p, qd)
        warm = at(active, jnp.arange(H) + lat - 1)  # to when it applies, less the step's shift
        u, ps, info = planner.step(ps._replace(plan=warm), start_q, start_qd)
        plan = ps.plan.at[0].set(u)  # the gate's hand-over, or the plan's own first action
        if gait:  # gait parameters are per rollout: hold the chosen ones over the plan
            plan = plan.at[:, nu:].set(plan[0, nu:])
        flight = (info.status, jnp.mean(info.kept < H), info.alarm)
        if not planning.latency_feedback:
            return ps._replace(plan=plan), (active, force, flight)
        # the policy at the states the model predicts along the new plan over its window
        states, _, _ = along(start_q, start_qd, lambda k, a, v: at(plan, k))
        ref = jnp.stack([planning.policy(a, v) for a, v in states])
        ok = jnp.all(jnp.isfinite(ref))  # a prediction gone astray: the plan as planned
        return ps._replace(plan=plan), (active, force, flight, refs[1],
                                        jnp.where(ok, ref, jnp.nan))

    ps, late = jax.lax.cond(step % lat == 0, replan, lambda ps: (ps, late), ps)
    active, in_force, _, *refs = late
    u = act(in_force, at(active, step % lat), refs[0][step % lat] if refs else None, q_aug, qd)
    return u, ps, late


def tracked(trace, settle_s: float = 0.5) -> np.ndarray:
    """The steps the tracking error is scored on: upright, and ``settle_s`` or more after the
    last command change (a trace's ``t``, ``command`` and ``fallen``; arrays or a saved trace)."""
    t, command = np.asarray(trace.t), np.asarray(trace.command)
    changed = np.r_[True, np.any(np.diff(command, axis=0) != 0, axis=1)]
    last = np.maximum.accumulate(np.where(changed, t, -np.inf))  # time of the latest change
    return ~np.asarray(trace.fallen) & (t - last >= settle_s)


def metrics(trace: Trace, settle_s: float = 0.5) -> dict:
    """Tracking RMSE while upright (after ``settle_s`` from each command change), fall, speed;
    the planner's fallbacks, its share of rollouts cut, the share of upright steps it drew
    its recovery candidates (``alarm_share``) and the share in which it handed the action to the
    policy (``distrust_share``, the model-trust gate); with the disturbance observer its mean
    estimate and how much the estimate's linear part jumps from one period to the next
    (``observer_step_rms``, m/s^2: what the sensors' noise puts into it)."""
    tr = jax.tree.map(np.asarray, trace)
    up = ~tr.fallen
    use = tracked(tr, settle_s)
    v_err = np.linalg.norm(tr.v_base[:, :2] - tr.command[:, :2], axis=1)
    w_err = np.abs(tr.w_base[:, 2] - tr.command[:, 2])
    rmse = lambda e: float(np.sqrt(np.mean(e[use] ** 2))) if use.any() else float("nan")
    fell = bool(tr.fallen.any())
    out = dict(vel_rmse=rmse(v_err), yaw_rmse=rmse(w_err), fell=fell,
               fall_s=float(tr.t[np.argmax(tr.fallen)]) if fell else None,
               mean_vx=float(tr.v_base[up, 0].mean()) if up.any() else float("nan"),
               upright_s=float(up.sum() * (tr.t[1] - tr.t[0]) if len(tr.t) > 1 else 0.0),
               fallbacks=int(np.isin(tr.status, [mppi.BAD_STATE, mppi.NO_FINITE_ROLLOUT]).sum()),
               distrust_share=float((tr.status[up] == mppi.DISTRUSTED).mean())
               if up.any() else float("nan"),
               cut_share=float(tr.cut.mean()),
               alarm_share=float(tr.alarm[up].mean()) if up.any() else float("nan"))
    if np.any(tr.disturbance != 0) and up.any():  # the observer's mean estimate while upright
        out["disturbance"] = [float(x) for x in tr.disturbance[up].mean(axis=0)]
        jumps = observer_step_rms(tr.disturbance, up)
        if jumps is not None:
            out["observer_step_rms"] = jumps
    if up.sum() >= 10 and tr.contact.shape[1] == 4:  # the quadruped gait the feet showed
        out["contact_gait"], out["contact_gait_score"] = gait_lib.classify_contacts(
            tr.contact[up])
    n_joint = tr.contact.shape[1] * 3
    if tr.contact.shape[1] == 4 and tr.action.shape[1] > n_joint and up.any():  # planned gait
        g = np.median(tr.action[up, n_joint:], axis=0)
        out["plan_freq"], out["plan_duty"] = float(g[0]), float(g[1])
        out["plan_gait"], out["plan_gait_dist"] = gait_lib.classify(g[2:])
    return out


def piece_errors(trace, starts, settle_s: float = 0.5) -> dict[str, np.ndarray]:
    """Each piece's tracking error, for a command :func:`schedule` ``starts [P]`` (s), over the
    steps :func:`tracked` scores within it: ``vel [P]`` the planar velocity RMSE (m/s), ``yaw
    [P]`` the yaw-rate RMSE (rad/s), ``offset [P, 3]`` the signed mean error (forward, lateral m/s;
    yaw rate rad/s: + is faster than asked); NaN where a piece scores none (a fall, or a piece
    shorter than ``settle_s``). Where :func:`metrics` gives one number per episode, this says
    under which commands the error arose, and which way (a trace's ``t``, ``command``,
    ``v_base``, ``w_base``, ``fallen``: arrays or a saved trace)."""
    use = tracked(trace, settle_s)
    t, command = np.asarray(trace.t), np.asarray(trace.command)
    v, w = np.asarray(trace.v_base), np.asarray(trace.w_base)
    starts = np.asarray(starts)
    piece = np.clip(np.searchsorted(starts, t, side="right") - 1, 0, len(starts) - 1)
    err = np.concatenate([v[:, :2] - command[:, :2], w[:, 2:3] - command[:, 2:3]], axis=1)
    n = np.bincount(piece[use], minlength=len(starts))

    def mean(x):  # per piece, over its scored steps
        s = np.bincount(piece[use], weights=x[use], minlength=len(starts))
        return np.where(n > 0, s / np.maximum(n, 1), np.nan)
    return dict(vel=np.sqrt(mean(np.sum(err[:, :2] ** 2, axis=1))),
                yaw=np.sqrt(mean(err[:, 2] ** 2)),
                offset=np.stack([mean(err[:, k]) for k in range(3)], axis=1))


def observer_step_rms(disturbance, up) -> float | None:
    """How much the observer's linear estimate jumps from one upright period to the next: the
    RMS of its change (m/s^2) over a trace's ``disturbance [T, 6]`` where ``up [T]``; None with
    fewer than three upright periods."""
    d = np.asarray(disturbance)[np.asarray(up)][:, :3]
    if len(d) < 3:
        return None
    return float(np.sqrt(np.mean(np.sum(np.diff(d, axis=0) ** 2, axis=1))))


class PolicyEpisode(NamedTuple):
    """The policy alone in a scenario, per control period (leading axis: the periods)."""

    t: jax.Array  # [T] s
    q_aug: jax.Array  # [T, nq + N_AUG] the state the policy saw (command and clock)
    qd: jax.Array  # [T, nv]
    u: jax.Array  # [T, nu] the policy's action
    ctrl: jax.Array  # [T, nu] the joint targets it became
    q_next: jax.Array  # [T, nq] the state one period later
    qd_next: jax.Array  # [T, nv]
    fallen: jax.Array  # [T] bool, after the period


def policy_episode(world: World, planning: Planning,
                   sense_gravity: bool = True) -> PolicyEpisode:
    """``planning``'s policy alone in a scenario's :class:`World` (:func:`scenario_world`), with
    its commands, pushes and tilt as the closed loop runs them (``sense_gravity`` as
    :func:`run_episode`'s): the states a planner would meet and the true step from each (issue
    19's diagnoses). Its own loop, not :func:`run_episode`'s: after a fall the policy keeps
    acting (the closed loop stops its effort) and ``fallen`` is each period's own (not latched),
    so a diagnosis sees every state the policy meets; while the robot is up the two act alike
    (``tests/test_control_closed_loop.py``: the same actions on a slope)."""
    if planning.policy is None:
        raise ValueError("policy_episode needs a planning with a policy")
    sm, mx, n_steps = world.sm, world.mx, world.n_steps
    starts, values, pushes, tilt = world.starts, world.values, world.pushes, world.tilt
    base = int(sm.mj.jnt_bodyid[0])
    dt = sm.robot.ctrl_dt

    @jax.jit
    def run():
        d0 = mjx.make_data(mx).replace(qpos=jnp.asarray(sm.info.qpos0).at[2].add(0.02))

        def body(carry, step):
            d, clock = carry
            t = step * dt
            q_aug = augment(d.qpos, command_at(starts, values, t), clock,
                            gravity=sensed_gravity(mx, t, tilt) if sense_gravity else None)
            u = planning.policy(q_aug, d.qvel)
            ctrl = planning.ctrl(q_aug, u)
            mx_t, d = world_at(mx, d, base, t, pushes, tilt)
            d2 = envs.physics_step(mx_t, sm.n_substeps, d, ctrl)
            clock = jnp.mod(clock + planning.clock_hz * dt, 1.0)
            return (d2, clock), PolicyEpisode(t, q_aug, d.qvel, u, ctrl, d2.qpos, d2.qvel,
                                              rollout_mjx.fallen(sm, d2.qpos))
        return jax.lax.scan(body, (d0, jnp.zeros(())), jnp.arange(n_steps))[1]

    return run()


def policy_alone(sm: sim_model.SimModel, sc: Scenario, policy_run: str, govern: bool = False
                 ) -> tuple[PolicyEpisode, envs.EnvConfig]:
    """The PPO policy of run ``policy_run`` alone in scenario ``sc`` (:func:`policy_episode` in
    its :func:`scenario_world`; ``govern``: the commands clipped to the policy's training range,
    :func:`stride_jax.control.scenarios.governed`, as the closed loop's ``--govern`` shows them):
    the episode, on the host, and the policy's task settings."""
    from stride_jax.control import ppo  # (the PPO stack loads only where a policy is read)
    policy, _, env_cfg = ppo.load_policy(policy_run)
    if govern:
        sc = governed(sc, env_cfg.commands.bounds())
    world = scenario_world(sm, sc)
    truth = make_planning(PlanningConfig(), env_cfg, sm,
                          envs.mjx_step_fn(sm.n_substeps, world.mx), policy, None)
    return jax.device_get(policy_episode(world, truth)), env_cfg


# ---------------------------------------------------------------------------------------------
# The planner's models.


def mjx_step_fn(sm: sim_model.SimModel, mx: mjx.Model) -> Callable:
    """``step(q, qd, ctrl, key) -> (q', qd')`` of an MJX model (the oracle's dynamics)."""
    return envs.mjx_step_fn(sm.n_substeps, mx)


def learned_model(run: str, sm: sim_model.SimModel, kernel: str = "xla") -> tuple[object, object]:
    """``(model, params)`` of a trained dynamics model (``stride train`` run folder), its
    networks run as ``kernel`` (``StructuredConfig.kernel``), checked to model ``sm``'s robot."""
    from stride_jax.dynamics import checkpoint
    model, params = checkpoint.load(run, kernel=kernel)
    q0 = jnp.asarray(sm.info.qpos0)
    try:  # shape check at the boundary: the run must model this robot
        jax.eval_shape(lambda: model.step(params, q0, jnp.zeros(sm.mj.nv),
                                          q0[7:], jax.random.key(0)))
    except ValueError as e:
        raise ValueError(f"{run} does not model robot {sm.robot.name}: {e}") from e
    return model, params


# float32 matrix products of a learned model's step: "" JAX's default (TF32 on recent NVIDIA
# GPUs), or one of jax.default_matmul_precision's names
PRECISIONS = ("", "default", "high", "highest")


def learned_step(model, params, precision: str = "", nfe: int | None = None) -> Callable:
    """``step(q, qd, ctrl, key, down=None)`` of ``model`` with ``params``, its float32 products
    traced at ``precision`` (:data:`PRECISIONS`; "": JAX's default); a gravity direction
    ``down`` reaches the models that take one (``models.takes_gravity``) and is left out for
    the others (``PlanningConfig.model_gravity``); ``nfe``: a generative model's evaluations per
    residual sample (None: as trained)."""
    if precision not in PRECISIONS:
        raise ValueError(f"precision {precision!r}: use one of {PRECISIONS}")
    if nfe is not None and nfe < 1:
        raise ValueError(f"nfe={nfe}: a residual sample needs at least one evaluation")
    from stride_jax.dynamics import models
    told = models.takes_gravity(model)

    def step(q, qd, ctrl, key, down=None):
        kw = {"down": down} if told and down is not None else {}
        if nfe is not None and model.stochastic:
            kw["nfe"] = nfe
        if not precision:
            return model.step(params, q, qd, ctrl, key, **kw)
        with jax.default_matmul_precision(precision):
            return model.step(params, q, qd, ctrl, key, **kw)
    return step


def learned_step_fn(run: str, sm: sim_model.SimModel, kernel: str = "xla",
                    precision: str = "", substeps: int = 0) -> Callable:
    """``step(q, qd, ctrl, key)`` of a trained dynamics model (:func:`learned_model`);
    ``substeps`` > 0: a structured model integrates each control period in as many substeps
    (``models.with_substeps``), a next-observation model predicts it at once as trained."""
    from stride_jax.dynamics import models

    model, params = learned_model(run, sm, kernel)
    if substeps and models.has_substeps(model):
        model = models.with_substeps(model, substeps)
    return learned_step(model, params, precision)
