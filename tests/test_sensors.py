"""A real robot's sensors (``stride_jax.sim.sensors``): each term's draw at its stated size, the
encoder's resolution, the glitches, a unit orientation; and the closed loop's controller seeing the
world through them (``run_episode(sensors=...)``, ``stride closed-loop --sensor-noise``) while the
world, the trace and the fall check keep the true state."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from mujoco import mjx

from stride_jax.control import envs, mppi
from stride_jax.control import episode as ep
from stride_jax.control import planning as planning_lib
from stride_jax.dynamics.integrate import quat_conj, quat_log, quat_mul
from stride_jax.gap import real
from stride_jax.jobs import closed_loop as cl
from stride_jax.sim import sensors

QUIET = sensors.SensorNoise(encoder_bits=0, encoder_std=0.0, velocity_std=0.0, torque_std=0.0,
                            base_drift=0.0, base_z_std=0.0, tilt_std=0.0, linvel_std=0.0,
                            gyro_std=0.0, outlier_rate=0.0)


def _draws(noise, q, qd, n=4000, floating=True):
    keys = jax.random.split(jax.random.key(3), n)
    return jax.device_get(jax.jit(jax.vmap(
        lambda k: sensors.measure(noise, q, qd, k, floating)))(keys))


def _state(nj=12, seed=0):
    rng = np.random.default_rng(seed)
    quat = rng.normal(size=4)
    q = np.concatenate([[0.3, -0.2, 0.31], quat / np.linalg.norm(quat), rng.normal(size=nj)])
    return jnp.asarray(q, jnp.float32), jnp.asarray(rng.normal(size=6 + nj), jnp.float32)


def test_each_term_draws_at_its_stated_size_and_nothing_else_moves():
    """One term at a time: the reading differs from the truth where that term acts, by draws of
    its standard deviation (4000 samples: within 5%), and nowhere else; the orientation stays a
    unit quaternion and its error is a rotation of the stated size per axis."""
    q, qd = _state()
    cases = {"encoder_std": (0.01, "qj"), "velocity_std": (0.3, "vj"), "base_z_std": (0.02, "z"),
             "linvel_std": (0.1, "lin"), "gyro_std": (0.05, "gyro"), "tilt_std": (0.03, "tilt")}
    for name, (std, where) in cases.items():
        mq, mqd = _draws(dataclasses.replace(QUIET, **{name: std}), q, qd)
        dq, dqd = mq - np.asarray(q), mqd - np.asarray(qd)
        parts = {"qj": dq[:, 7:], "vj": dqd[:, 6:], "z": dq[:, 2:3], "lin": dqd[:, :3],
                 "gyro": dqd[:, 3:6]}
        if where == "tilt":
            rot = jax.vmap(lambda a: quat_log(quat_mul(quat_conj(q[3:7]), a)))(jnp.asarray(mq[:, 3:7]))
            parts["tilt"] = np.asarray(rot)
            np.testing.assert_allclose(np.linalg.norm(mq[:, 3:7], axis=1), 1.0, atol=1e-6)
        got = parts.pop(where)
        assert abs(got.std() / std - 1) < 0.05, (name, got.std())
        assert abs(got.mean()) < 0.1 * std, (name, got.mean())
        for other, x in parts.items():  # every other coordinate as it was
            np.testing.assert_allclose(x, 0.0, atol=1e-6, err_msg=f"{name} moved {other}")
        if where != "tilt":
            np.testing.assert_allclose(dq[:, 3:7], 0.0, atol=1e-6)
        np.testing.assert_array_equal(dq[:, :2], 0.0)  # the horizontal position: not read


def test_the_encoder_quantises_and_the_glitches_come_at_their_rate_and_size():
    q, qd = _state()
    res = 2 * np.pi / 2 ** 10
    mq, _ = _draws(dataclasses.replace(QUIET, encoder_bits=10), q, qd, n=8)
    np.testing.assert_allclose(mq[:, 7:] / res, np.round(mq[:, 7:] / res), atol=1e-3)
    assert np.all(np.abs(mq[:, 7:] - np.asarray(q[7:])) <= res / 2 + 1e-6)
    _, mqd = _draws(dataclasses.replace(QUIET, outlier_rate=0.05), q, qd)
    off = np.abs(mqd[:, 6:] - np.asarray(qd[6:]))
    hit = off > 1e-6
    assert abs(hit.mean() / 0.05 - 1) < 0.1
    assert off[hit].min() >= sensors.SPIKE[0] - 1e-4 and off[hit].max() <= sensors.SPIKE[1] + 1e-4
    np.testing.assert_array_equal(mqd[:, :6], np.broadcast_to(np.asarray(qd[:6]), mqd[:, :6].shape))


def test_a_fixed_base_robot_has_joints_only_and_quiet_sensors_read_the_truth():
    q, qd = jnp.asarray([0.4, -1.0]), jnp.asarray([2.0, 0.5])
    mq, mqd = _draws(dataclasses.replace(QUIET, encoder_std=0.01, linvel_std=1.0, tilt_std=1.0),
                     q, qd, n=2000, floating=False)
    assert abs((mq - np.asarray(q)).std() / 0.01 - 1) < 0.1
    np.testing.assert_array_equal(mqd, np.broadcast_to(np.asarray(qd), mqd.shape))  # no base
    fq, fqd = _state()
    mq, mqd = _draws(QUIET, fq, fqd, n=3)
    np.testing.assert_array_equal(mq, np.broadcast_to(np.asarray(fq), mq.shape))
    np.testing.assert_array_equal(mqd, np.broadcast_to(np.asarray(fqd), mqd.shape))


def test_scaling_and_bad_terms():
    s = sensors.SensorNoise().scaled(3.0)
    assert s.linvel_std == pytest.approx(3 * sensors.SensorNoise().linvel_std)
    assert (s.encoder_bits, s.outlier_rate) == (14, sensors.SensorNoise().outlier_rate)
    assert real.SensorNoise is sensors.SensorNoise  # the gap's logs and the closed loop: one sensor
    for bad in (dict(gyro_std=-0.1), dict(linvel_std=float("nan")), dict(outlier_rate=1.5),
                dict(encoder_bits=-1), dict(encoder_bits=2.5)):
        with pytest.raises(ValueError, match=next(iter(bad))):
            sensors.SensorNoise(**bad)
    with pytest.raises(ValueError, match="factor"):
        sensors.SensorNoise().scaled(-1.0)
    with pytest.raises(ValueError, match="sensor.noise"):
        cl.ClosedLoopConfig(sensor_noise=float("nan"))
    with pytest.raises(ValueError, match="only --sensor-noise > 0 uses"):
        cl.ClosedLoopConfig(sensors=sensors.SensorNoise(gyro_std=0.5))
    cfg = cl.ClosedLoopConfig(sensor_noise=3.0, rough_cm=2)
    assert cl.scenario(cfg, "rough").name == "rough2_noise3"


def _watching_planner(nu: int, seen: list) -> mppi.Planner:
    """A "planner" that stands still (its actions zero, so the world does not depend on what it
    sees) and reports each period's ``(q_aug, qd)`` to ``seen`` on the host."""
    def init(key, plan=None):
        return mppi.MPPIState(jnp.zeros((4, nu)), key, held=jnp.zeros((), jnp.int32))

    def step(state, q_aug, qd):
        jax.debug.callback(lambda a, v: seen.append((np.asarray(a), np.asarray(v))), q_aug, qd,
                           ordered=True)
        z = jnp.zeros(1)
        info = mppi.Info(z, z, z[0], state.plan, jnp.zeros((), jnp.int32), state.plan[None], z,
                         jnp.full(1, 4, jnp.int32), jnp.zeros((), bool))
        return state.plan[0], state, info

    return mppi.Planner(init, step)


def test_the_controller_sees_the_world_through_the_sensors_and_the_world_keeps_the_truth(go1):
    """Go1 in MJX with a planner that stands still: through noisy sensors the world and its
    trace are the exact-state run's (the actions are the same; to float rounding, another
    program), the planner sees each period's
    true state measured with that period's draw (``measure`` with the episode's sensor key), the
    observer's estimate and the integral action's command move with the readings (both read the
    measured velocities). (Quiet sensors read the truth: the test above, on ``measure``.)"""
    nu, n = go1.info.nu, 6
    mx = mjx.put_model(go1.mj)
    w = cl.scenario_world(go1, dataclasses.replace(cl.SCENARIOS["walk"],
                                                   seconds=n * go1.robot.ctrl_dt))
    planning = planning_lib.make_planning(
        planning_lib.PlanningConfig(observer_gain=0.3, velocity_integral=1.0,
                                    velocity_integral_settle_s=0.0),
        envs.config("go1"), go1, cl.mjx_step_fn(go1, mx))
    key = jax.random.key(4)
    noise = dataclasses.replace(QUIET, linvel_std=0.2, velocity_std=0.5, tilt_std=0.02)
    runs = {}
    for label, sens in (("exact", None), ("noisy", noise)):
        seen = []
        trace = jax.device_get(jax.jit(lambda k: ep.run_episode(
            w.sm, w.mx, w.slots, planning, _watching_planner(nu, seen), n, w.starts, w.values, k,
            sensors=sens))(key))
        runs[label] = (trace, seen)
    (exact, truth), (noisy, n_seen) = runs["exact"], runs["noisy"]
    for f in ("v_base", "w_base", "height", "action", "contact"):  # the world: the truth's
        np.testing.assert_allclose(getattr(noisy, f), getattr(exact, f), atol=1e-5, err_msg=f)
    nq = go1.mj.nq
    sense_key = jax.random.fold_in(key, 0x5E45)
    for k, ((qa, qd), (ta, td)) in enumerate(zip(n_seen, truth)):
        mq, mqd = sensors.measure(noise, jnp.asarray(ta[:nq]), jnp.asarray(td),
                                  jax.random.fold_in(sense_key, k), True)
        np.testing.assert_allclose(qa[:nq], mq, atol=1e-6)
        np.testing.assert_allclose(qd, mqd, atol=1e-6)
    assert not np.allclose(noisy.disturbance, exact.disturbance, atol=1e-3)
    # the observer's first update, by hand from the readings: the state and velocity the planner
    # saw in period 0 and the velocity it sees in period 1 (the same draw)
    (a0, v0), (_, v1) = n_seen[0], n_seen[1]
    first = planning_lib.update_disturbance(
        planning, jnp.asarray(a0), jnp.asarray(v0), jnp.zeros(nu), jnp.asarray(v1),
        go1.robot.ctrl_dt, jax.random.fold_in(jax.random.fold_in(key, 0x0B5E), 0))
    np.testing.assert_allclose(noisy.disturbance[0], first, rtol=1e-4, atol=1e-4)
    # the row's observer_step_rms: how much the estimate's linear part jumps per period
    jumps = np.diff(np.asarray(noisy.disturbance)[:, :3], axis=0)
    rms = ep.metrics(noisy, 0.0)["observer_step_rms"]
    assert rms == pytest.approx(float(np.sqrt(np.mean(np.sum(jumps ** 2, axis=1)))), rel=1e-6)
    assert rms > ep.metrics(exact, 0.0).get("observer_step_rms", 0.0)
    cmd = lambda seen: np.stack([planning_lib.split(jnp.asarray(a), nq).command for a, _ in seen])
    assert not np.allclose(cmd(n_seen)[2:, :2], cmd(truth)[2:, :2], atol=1e-4)
    with pytest.raises(ValueError, match="record pairs"):
        ep.run_episode(w.sm, w.mx, w.slots, planning, _watching_planner(nu, []), 1, w.starts,
                       w.values, key, record=lambda *a: 0, sensors=noise)


def test_the_velocity_filter_blends_the_observers_prediction_into_what_the_controller_acts_on(go1):
    """``planning.velocity_filter`` f: from the second period on the controller acts on the
    base's linear velocity ``measured + f (predicted - measured)`` (every other velocity as
    measured), the prediction the observer made in the period
    before (the model's step from what the controller then acted on); the first period acts on
    the measurement; the world is the unfiltered run's (a planner that stands still). Without
    the observer it is an error."""
    nu, n, f = go1.info.nu, 4, 0.75
    mx = mjx.put_model(go1.mj)
    w = cl.scenario_world(go1, dataclasses.replace(cl.SCENARIOS["walk"],
                                                   seconds=n * go1.robot.ctrl_dt))
    key = jax.random.key(5)
    noise = dataclasses.replace(QUIET, linvel_std=0.2, velocity_std=0.5)
    seen = {}
    for share in (0.0, f):
        planning = planning_lib.make_planning(
            planning_lib.PlanningConfig(observer_gain=0.3, velocity_filter=share),
            envs.config("go1"), go1, cl.mjx_step_fn(go1, mx))
        seen[share] = []
        trace = jax.device_get(jax.jit(lambda k: ep.run_episode(
            w.sm, w.mx, w.slots, planning, _watching_planner(nu, seen[share]), n, w.starts,
            w.values, k, sensors=noise))(key))
        seen[share].append(trace)
    (*raw, plain), (*filt, trace) = seen[0.0], seen[f]
    np.testing.assert_allclose(trace.height, plain.height, atol=1e-5)
    np.testing.assert_allclose(filt[0][1], raw[0][1], atol=1e-6)  # period 0: the measurement
    for k in range(1, n):
        (a_prev, v_prev), (_, v_meas) = filt[k - 1], raw[k]  # raw: the same draws, unblended
        _, pred = planning_lib.observe_step(
            planning, jnp.asarray(a_prev), jnp.asarray(v_prev), jnp.zeros(nu),
            jnp.asarray(v_meas), go1.robot.ctrl_dt,
            jax.random.fold_in(jax.random.fold_in(key, 0x0B5E), k - 1))
        want = v_meas.copy()
        want[:3] += f * (np.asarray(pred)[:3] - v_meas[:3])  # the base's linear velocity alone
        np.testing.assert_allclose(filt[k][1], want, atol=1e-4, err_msg=f"period {k}")
        assert np.abs(filt[k][1][:3] - v_meas[:3]).max() > 1e-3  # the blend moved it
    with pytest.raises(ValueError, match="needs observer_gain > 0"):
        planning_lib.PlanningConfig(velocity_filter=0.5)
    with pytest.raises(ValueError, match=r"in \[0, 1\)"):
        planning_lib.PlanningConfig(observer_gain=0.3, velocity_filter=1.0)
