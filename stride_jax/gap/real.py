"""A stand-in for the real robot: the robot's explorer run on the nominal model with hidden effects,
written in the log format, optionally through a real robot's sensors.

The physics is CPU MuJoCo (see :mod:`stride_jax.gap.sim` for why it stands in for MJX). Episode
draws (explorer parameters, initial states) reuse the robot's own explorer with JAX keys, so a
seed gives the same commands and starts whatever effect is planted.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from stride_jax.gap import effects, logs, sim
from stride_jax.sim.model import SimModel
from stride_jax.sim.sensors import SPIKE, SensorNoise  # (the logs' sensors; re-exported)
from stride_jax.sim.rollout_mjx import fallen


def _quat_mul(a, b):
    w1, x1, y1, z1 = np.moveaxis(a, -1, 0)
    w2, x2, y2, z2 = np.moveaxis(b, -1, 0)
    return np.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], -1)


def add_noise(sm: SimModel, tr: logs.Trajectory, noise: SensorNoise, rng: np.random.Generator
              ) -> logs.Trajectory:
    """The trajectory as a real robot's sensors and state estimator would log it."""
    lay = logs.layout(sm)
    q, qd = tr.q.copy(), tr.qd.copy()
    T = len(q)
    qj = q[:, lay.qadr] + noise.encoder_std * rng.standard_normal((T, len(lay.qadr)))
    if noise.encoder_bits:
        res = 2 * np.pi / 2 ** noise.encoder_bits
        qj = np.round(qj / res) * res
    q[:, lay.qadr] = qj
    vj = qd[:, lay.vadr] + noise.velocity_std * rng.standard_normal((T, len(lay.vadr)))
    spikes = rng.random(vj.shape) < noise.outlier_rate
    vj[spikes] += rng.choice([-1, 1], spikes.sum()) * rng.uniform(*SPIKE, spikes.sum())
    qd[:, lay.vadr] = vj
    if sm.robot.floating_base:
        q[:, :2] += np.cumsum(noise.base_drift * rng.standard_normal((T, 2)), 0)
        q[:, 2] += noise.base_z_std * rng.standard_normal(T)
        dq = np.concatenate([np.ones((T, 1)), 0.5 * noise.tilt_std * rng.standard_normal((T, 3))], 1)
        quat = _quat_mul(q[:, 3:7], dq)
        q[:, 3:7] = quat / np.linalg.norm(quat, axis=1, keepdims=True)
        qd[:, :3] += noise.linvel_std * rng.standard_normal((T, 3))
        qd[:, 3:6] += noise.gyro_std * rng.standard_normal((T, 3))
    tau = None if tr.tau is None else tr.tau + noise.torque_std * rng.standard_normal(tr.tau.shape)
    imu = tr.imu
    if imu is not None:
        imu = imu + np.concatenate([0.05 * rng.standard_normal((T, 3)),
                                    noise.gyro_std * rng.standard_normal((T, 3))], 1)
    return tr._replace(q=q, qd=qd, tau=tau, imu=imu)


@functools.lru_cache(maxsize=None)
def _explorer(sm: SimModel):
    info, ex = sm.info, sm.robot.explorer

    def draw(k):
        params = ex.sample(k, info)
        q, qd = ex.reset(params, info)
        return params, q, qd

    act = jax.vmap(lambda p, s, q, qd: ex.act(p, info, s, q, qd), in_axes=(0, None, 0, 0))
    return jax.jit(jax.vmap(draw)), jax.jit(act)


def generate(sm: SimModel, applied: effects.Applied | None, n_traj: int, n_steps: int, seed: int,
             noise: SensorNoise | None = None, min_steps: int = 20
             ) -> tuple[list[logs.Trajectory], list[logs.Trajectory]]:
    """Runs the robot's explorer with the hidden ``applied`` effects for ``n_traj`` episodes.

    Returns ``(clean, logged)``: the true trajectories and what the sensors log (the same list when
    ``noise`` is None). Each is cut where the robot falls; episodes shorter than ``min_steps`` are
    dropped. The logged measured torque is the actuator force; the IMU is ideal before noise.
    """
    plan = effects.build(sm, applied)
    draw, act = _explorer(sm)
    params, q0, qd0 = draw(jax.random.split(jax.random.PRNGKey(seed), n_traj))
    policy = lambda t, q, qd: np.asarray(act(params, t, jnp.asarray(q, jnp.float32),
                                             jnp.asarray(qd, jnp.float32)))
    res = sim.closed_loop(sm, plan, np.asarray(q0, np.float64), np.asarray(qd0, np.float64), policy,
                          n_steps, fallen=lambda q: fallen(sm, q, np))
    clean = []
    for b in range(n_traj):
        n = int(res["valid"][b].sum())
        if n < min_steps:
            continue
        q, qd = res["q"][b, :n], res["qd"][b, :n]
        imu = logs.imu_from_sim(q, qd, res["qdd"][b, :n], sm.mj.opt.gravity) if (
            sm.robot.floating_base) else None
        clean.append(logs.Trajectory(f"traj_{b:03d}", res["t"][:n], q, qd, res["cmd"][b, :n],
                                     res["tau"][b, :n], imu))
    if noise is None:
        return clean, clean
    rng = np.random.default_rng(seed + 7919)
    return clean, [add_noise(sm, tr, noise, rng) for tr in clean]
