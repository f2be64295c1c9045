"""Unitree Go1 (MuJoCo Menagerie ``unitree_go1``, ``scene.xml``) with a parameterised gait library.

MJX-ready edits (as MuJoCo Playground makes them): pyramidal friction cones (MJX rejects the
shipped condim=1 geoms under elliptic cones), floor contacts for the four feet only (the full
collision set has ~1100 contact slots and runs ~40x slower), condim 3 at the feet, a 4 ms timestep,
and the Euler integrator without implicit damping so that the next velocity is exactly
``qvel + dt * qacc``.

Solver: up to 15 Newton iterations (15 line-search steps). Playground's 1-4 iterations are fast but
leave the constraint solve unconverged at impacts, and then MuJoCo's own quantities break the
equation of motion the dataset promises (M qdd != tau + passive + constraint - bias). Measured on
600 exploration steps: 14% of steps off by more than 1e-3 (relative) at 4 iterations, 0.8% at 10,
none at 12 or more. The solver stops early once converged, so easy steps stay cheap.

Exploration: a periodic joint-space reference per leg (stance sweep of the thigh, swing with knee
lift) with gait-specific phase offsets -- trot, pronk, bound, pace -- and random frequency, duty
factor, stride, lift, lateral/turning offsets and target noise, tracked by the position servos
(kp = 100 N m/rad, the joints' own damping of 1-2 N m s/rad).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from stride_jax.robots import base

LEGS = ("FR", "FL", "RR", "RL")
GAITS = ("trot", "pronk", "bound", "pace")
# Phase offset of each leg (FR, FL, RR, RL) as a fraction of the gait cycle.
GAIT_PHASES = np.array([
    [0.0, 0.5, 0.5, 0.0],  # trot: diagonal pairs
    [0.0, 0.0, 0.0, 0.0],  # pronk: all together
    [0.0, 0.0, 0.5, 0.5],  # bound: front pair, then rear pair
    [0.0, 0.5, 0.0, 0.5],  # pace: lateral pairs
], dtype=np.float32)
STAND = np.array([0.0, 0.9, -1.8], dtype=np.float32)  # abduction, thigh, calf of the home pose


class GaitParams(NamedTuple):
    key: jax.Array
    gait: jax.Array  # int, index into GAITS
    freq: jax.Array  # gait frequency (Hz)
    duty: jax.Array  # stance fraction of the cycle
    stride: jax.Array  # thigh sweep amplitude (rad)
    lift: jax.Array  # knee flexion at mid-swing (rad)
    lateral: jax.Array  # abduction offset, all legs (rad)
    turn: jax.Array  # stride difference left vs right (fraction)
    noise: jax.Array  # std of the white noise on joint targets (rad)
    joint_noise0: jax.Array  # [12] initial joint offsets (rad)


class GaitExplorer:
    """Trot, pronk, bound and pace from one phase-offset gait reference, with noise."""

    def sample(self, key: jax.Array, info: base.ModelInfo) -> GaitParams:
        ks = jax.random.split(key, 10)
        u = lambda k, lo, hi: jax.random.uniform(k, minval=lo, maxval=hi)
        return GaitParams(
            key=ks[0],
            gait=jax.random.randint(ks[1], (), 0, len(GAITS)),
            freq=u(ks[2], 1.5, 3.0),
            duty=u(ks[3], 0.4, 0.65),
            stride=u(ks[4], 0.0, 0.3),
            lift=u(ks[5], 0.2, 0.7),
            lateral=u(ks[6], -0.1, 0.1),
            turn=u(ks[7], -0.5, 0.5),
            noise=u(ks[8], 0.0, 0.08),
            joint_noise0=0.05 * jax.random.normal(ks[9], (12,)),
        )

    def reset(self, params: GaitParams, info: base.ModelInfo):
        # The home keyframe leaves the feet 18 mm inside the floor: start 2 mm above it instead.
        qpos = jnp.asarray(info.qpos0).at[2].add(0.02).at[7:].add(params.joint_noise0)
        return qpos, jnp.zeros(info.nv)

    def act(self, params: GaitParams, info: base.ModelInfo, step, qpos, qvel):
        t = step * info.ctrl_dt
        phase = jnp.mod(params.freq * t + jnp.asarray(GAIT_PHASES)[params.gait], 1.0)  # [4]
        in_stance = phase < params.duty
        u_stance = phase / params.duty  # 0 -> 1 through stance
        u_swing = (phase - params.duty) / (1.0 - params.duty)  # 0 -> 1 through swing
        side = jnp.array([-1.0, 1.0, -1.0, 1.0])  # right legs -1, left legs +1
        stride = params.stride * (1.0 + params.turn * side)
        # Stance sweeps the thigh one way (foot moves back under the body), swing brings it forward.
        sweep = jnp.where(in_stance, 1.0 - 2.0 * u_stance, -1.0 + 2.0 * u_swing)
        lift = jnp.where(in_stance, 0.0, jnp.sin(jnp.pi * u_swing)) * params.lift
        abduction = jnp.full(4, STAND[0]) + params.lateral * side
        thigh = STAND[1] - stride * sweep + 0.5 * lift
        calf = STAND[2] - lift
        target = jnp.stack([abduction, thigh, calf], axis=-1).reshape(12)
        noise = params.noise * jax.random.normal(jax.random.fold_in(params.key, step), (12,))
        return jnp.clip(target + noise, info.ctrl_lo, info.ctrl_hi)


def edit_spec(spec: mujoco.MjSpec) -> None:
    """Pyramidal cones, feet-only floor contacts, 4 ms Euler steps with a converged Newton solve."""
    spec.option.cone = mujoco.mjtCone.mjCONE_PYRAMIDAL
    spec.option.timestep = 0.004
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_EULER
    spec.option.disableflags |= mujoco.mjtDisableBit.mjDSBL_EULERDAMP
    spec.option.iterations = 15
    spec.option.ls_iterations = 15
    for geom in spec.geoms:
        if geom.name == "floor":
            geom.contype, geom.conaffinity = 1, 0
        elif geom.name in LEGS:
            geom.contype, geom.conaffinity, geom.condim = 0, 1, 3
        else:
            geom.contype, geom.conaffinity = 0, 0


GO1 = base.Robot(
    name="go1",
    source="MuJoCo Menagerie unitree_go1, entry 'scene' (scene.xml)",
    load_spec=lambda: base.menagerie_spec("unitree_go1", "scene", "go1"),
    edit_spec=edit_spec,
    joints=tuple(f"{leg}_{j}_joint" for leg in LEGS for j in ("hip", "thigh", "calf")),
    feet=tuple(base.Foot(leg, (leg,), leg) for leg in LEGS),
    base_body="trunk",
    floating_base=True,
    ctrl_dt=0.02,
    home_key="home",
    kp=(100.0,) * 12,  # the servos' own gains (go1.xml <position kp=100>)
    kd=(0.0,) * 12,  # no servo damping; the joints carry damping 1-2 N m s/rad
    explorer=GaitExplorer(),
    randomization=base.Randomization(
        friction=(0.4, 1.25), softness=(1.0, 2.5), payload_kg=(0.0, 2.0), push_n=(0.0, 40.0),
        push_s=(0.1, 0.3)),
    episode_s=10.0,
    min_base_height=0.12,
    max_tilt=1.0,
)
