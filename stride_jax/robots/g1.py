"""Unitree G1 humanoid, 29 DoF (MuJoCo Menagerie ``unitree_g1``, entry ``scene_mjx``).

MJX-ready edits: of the 49 explicit contact pairs of ``scene_mjx`` only the six foot-floor pairs
are kept (three capsules per sole; falls end the episode instead of being simulated on the floor).
Integrator and timestep stay as shipped (implicitfast, 4 ms); the solver gets up to 15 Newton
iterations and 15 line-search steps instead of 5 and 8: with the shipped settings 40% of the
exploration steps violate the equation of motion by more than 1e-3 (relative; 14% still at 10
iterations, none at 15), i.e. the recorded constraint forces would not be the ones simulated.

Servo gains: the MJX file's ankle servos (kp = 20 N m/rad) cannot hold the robot up without a
balance policy -- it falls from the home pose within 1-2 s -- and data of a lying robot is not
walking data. We raise the leg gains (hip 150, knee 200, ankle 250 N m/rad; damping 4/4/5) while
keeping every torque limit as shipped; with them the robot stands, shifts its weight and takes
small steps. Walking proper comes from the PPO policy of the control package.

Balance: the ankles' targets lean against the pelvis's roll and pitch (proportional and rate
feedback; gains picked on a grid for the fraction of upright steps: standing and weight shifting
stay up over 5 s, stepping in place for ~80% of the steps). Exploration modes, drawn per episode: standing still with target noise, lateral weight shifting
(hip/ankle roll sway), and stepping in place (the unloaded leg lifts while the weight is on the
other), each with random arm swinging and random crouch depth.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco

from stride_jax.robots import base

SIDES = ("left", "right")
LEG = ("hip_pitch", "hip_roll", "hip_yaw", "knee", "ankle_pitch", "ankle_roll")
WAIST = ("waist_yaw", "waist_roll", "waist_pitch")
ARM = ("shoulder_pitch", "shoulder_roll", "shoulder_yaw", "elbow", "wrist_roll", "wrist_pitch",
       "wrist_yaw")
JOINTS = (tuple(f"{s}_{j}_joint" for s in SIDES for j in LEG) + tuple(f"{j}_joint" for j in WAIST)
          + tuple(f"{s}_{j}_joint" for s in SIDES for j in ARM))
# Actuator indices (actuators follow JOINTS).
_L = {j: i for i, j in enumerate(LEG)}
_R = {j: 6 + i for i, j in enumerate(LEG)}
_ARMS = list(range(15, 29))


def _gains(joint: str) -> tuple[float, float]:
    if "ankle" in joint:
        return 250.0, 5.0
    if "knee" in joint:
        return 200.0, 4.0
    if "hip" in joint or "waist" in joint:
        return 150.0, 4.0
    return 40.0, 2.0  # arms: as light as shipped for the wrists, a bit stiffer at the shoulders


ROLL_GAIN = 1.0  # rad of ankle/hip roll target per rad of pelvis roll
ROLL_RATE_GAIN = 0.05  # per rad/s of pelvis roll rate
PITCH_GAIN = 1.0  # rad of ankle pitch target per rad of pelvis pitch
PITCH_RATE_GAIN = 0.1  # rad of ankle pitch target per rad/s of pelvis pitch rate


def _roll_pitch(quat: jax.Array) -> tuple[jax.Array, jax.Array]:
    w, x, y, z = quat
    roll = jnp.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = jnp.arcsin(jnp.clip(2 * (w * y - z * x), -1.0, 1.0))
    return roll, pitch


class BalanceParams(NamedTuple):
    key: jax.Array
    mode: jax.Array  # 0 stand, 1 weight shift, 2 step in place
    sway: jax.Array  # hip-roll sway amplitude (rad)
    freq: jax.Array  # sway / stepping frequency (Hz)
    lift: jax.Array  # swing-leg flexion when stepping (rad)
    crouch: jax.Array  # extra knee flexion (rad)
    arm_amp: jax.Array  # [14] arm swing amplitudes (rad)
    arm_freq: jax.Array  # [14] (Hz)
    noise: jax.Array  # target noise std (rad)


class BalanceExplorer:
    """Standing, weight shifting and stepping in place around the bent-knee pose."""

    def sample(self, key: jax.Array, info: base.ModelInfo) -> BalanceParams:
        ks = jax.random.split(key, 9)
        u = lambda k, lo, hi, shape=(): jax.random.uniform(k, shape, minval=lo, maxval=hi)
        mode = jax.random.randint(ks[1], (), 0, 3)
        return BalanceParams(
            key=ks[0],
            mode=mode,
            sway=jnp.where(mode > 0, u(ks[2], 0.01, 0.035), 0.0),
            freq=u(ks[3], 0.4, 1.0),
            lift=jnp.where(mode == 2, u(ks[4], 0.02, 0.1), 0.0),
            crouch=u(ks[5], 0.0, 0.2),
            arm_amp=u(ks[6], 0.0, 0.3, (14,)),
            arm_freq=u(ks[7], 0.2, 1.5, (14,)),
            noise=u(ks[8], 0.0, 0.03),
        )

    def reset(self, params: BalanceParams, info: base.ModelInfo):
        return jnp.asarray(info.qpos0), jnp.zeros(info.nv)

    def act(self, params: BalanceParams, info: base.ModelInfo, step, qpos, qvel):
        t = step * info.ctrl_dt
        target = jnp.asarray(info.qpos0)[7:]
        s = jnp.sin(2 * jnp.pi * params.freq * t)
        # Sway: both hips roll one way, both ankles roll back, moving the pelvis over one foot.
        for leg in (_L, _R):
            target = target.at[leg["hip_roll"]].add(params.sway * s)
            target = target.at[leg["ankle_roll"]].add(-params.sway * s)
            target = target.at[leg["knee"]].add(params.crouch)
            target = target.at[leg["hip_pitch"]].add(-0.5 * params.crouch)
            target = target.at[leg["ankle_pitch"]].add(-0.5 * params.crouch)
        # Stepping: lift the leg that the sway has unloaded (left when the pelvis is over the right).
        for leg, unloaded in ((_L, jnp.maximum(-s, 0.0)), (_R, jnp.maximum(s, 0.0))):
            lift = params.lift * unloaded
            target = target.at[leg["hip_pitch"]].add(-lift)
            target = target.at[leg["knee"]].add(2.0 * lift)
            target = target.at[leg["ankle_pitch"]].add(-lift)
        # Balance: tilt the ankles (and counter-roll the hips) against the pelvis's roll and pitch
        # (free-joint angular velocity qvel[3:6] is in the pelvis frame).
        roll, pitch = _roll_pitch(qpos[3:7])
        for leg in (_L, _R):
            roll_fb = ROLL_GAIN * roll + ROLL_RATE_GAIN * qvel[3]
            target = target.at[leg["ankle_roll"]].add(roll_fb)
            target = target.at[leg["hip_roll"]].add(-roll_fb)
            target = target.at[leg["ankle_pitch"]].add(PITCH_GAIN * pitch
                                                       + PITCH_RATE_GAIN * qvel[4])
        arms = params.arm_amp * jnp.sin(2 * jnp.pi * params.arm_freq * t)
        target = target.at[jnp.array(_ARMS)].add(arms)
        noise = params.noise * jax.random.normal(jax.random.fold_in(params.key, step), target.shape)
        return jnp.clip(target + noise, info.ctrl_lo, info.ctrl_hi)


def edit_spec(spec: mujoco.MjSpec) -> None:
    """Keep only the foot-floor contact pairs; converged solver; data-collection servo gains."""
    spec.option.iterations = 15
    spec.option.ls_iterations = 15
    for pair in list(spec.pairs):
        if not ("foot" in pair.name and pair.name.endswith("_floor")):
            spec.delete(pair)
    for act in spec.actuators:
        kp, kd = _gains(act.name)
        act.gainprm[0] = kp
        act.biasprm[1] = -kp
        act.biasprm[2] = -kd


G1 = base.Robot(
    name="g1",
    source="MuJoCo Menagerie unitree_g1 (29 DoF, rev 1.0), entry 'scene_mjx'",
    load_spec=lambda: base.menagerie_spec("unitree_g1", "scene_mjx", "g1"),
    edit_spec=edit_spec,
    joints=JOINTS,
    feet=(base.Foot("left", tuple(f"left_foot{i}_collision" for i in (1, 2, 3)), "left_foot"),
          base.Foot("right", tuple(f"right_foot{i}_collision" for i in (1, 2, 3)), "right_foot")),
    base_body="pelvis",
    floating_base=True,
    ctrl_dt=0.02,
    home_key="knees_bent",
    kp=tuple(_gains(j)[0] for j in JOINTS),
    kd=tuple(_gains(j)[1] for j in JOINTS),
    explorer=BalanceExplorer(),
    randomization=base.Randomization(
        friction=(0.5, 1.25), softness=(1.0, 2.0), payload_kg=(0.0, 3.0), push_n=(0.0, 15.0),
        push_s=(0.1, 0.2)),
    episode_s=10.0,
    min_base_height=0.5,
    max_tilt=0.8,
)
