"""Velocity-command locomotion environments in MJX, with the Brax ``Env`` API that PPO trains on.

The robots are our own definitions (``stride_jax.sim.model.load``): feet-only contacts, pyramidal
cones, the robots' PD position servos. An action ``a`` in ``[-1, 1]^nu`` is a joint-target offset
around the home pose: ``ctrl = clip(home + action_scale * a, ctrl range)``, held for one control
period (``n_substeps`` simulation steps).

A command is ``(vx, vy, yaw rate)`` in the base frame (m/s, m/s, rad/s), drawn per episode and
re-drawn every ``resample_s`` seconds. The reward is a dict of named terms with scales, as MuJoCo
Playground writes it (Rudin et al. 2022 for the terms):

    r = max(0, dt * sum_i scale_i * term_i)

(the clip keeps rewards non-negative, so ending an episode early only loses reward). Every term's
scaled contribution is reported in ``state.metrics['reward/<name>']``.

The observation is a function of the state and the command alone (:func:`observe`):
``[v_base (3), w_base (3), gravity_base (3), q_joints - home (nu), qd_joints (nu), command (3)]``
plus, for robots with a gait clock (the G1), ``[cos 2 pi c, sin 2 pi c]`` -- so that a planner
that holds ``(q, qd, command)`` can query the policy (:func:`observation_fn`).

Written for one world; :func:`stride_jax.control.wrappers.wrap_for_training` vmaps it, counts
episodes, and resets finished worlds to a freshly drawn state and command (Brax's own auto-reset
returns every world to its first state, which would fix each world's command and start for the
whole run).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Callable

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from brax.envs import base as brax_base
from mujoco import mjx

from stride_jax.control import gait as gait_lib, scenarios
from stride_jax.dynamics.lagrangian import WORLD_DOWN
from stride_jax.sim import randomize, rollout_mjx, sensors
from stride_jax.sim import model as sim_model


@dataclasses.dataclass(frozen=True)
class Commands:
    """Command distribution: uniform ranges (base frame), a share of stand-still commands."""

    forward: tuple[float, float] = (0.0, 2.0)  # m/s
    lateral: tuple[float, float] = (-0.5, 0.5)  # m/s
    yaw: tuple[float, float] = (-1.0, 1.0)  # rad/s
    zero_prob: float = 0.1
    resample_s: float = 5.0

    def bounds(self) -> tuple[jax.Array, jax.Array]:
        """``(lo [3], hi [3])`` of (vx, vy, yaw rate): the ranges commands are drawn from."""
        return (jnp.array([self.forward[0], self.lateral[0], self.yaw[0]]),
                jnp.array([self.forward[1], self.lateral[1], self.yaw[1]]))


@dataclasses.dataclass(frozen=True)
class RewardScales:
    """Scale of each reward term (0 disables it). Terms (all per control step, before ``* dt``):

    tracking_lin_vel: exp(-|cmd_xy - v_xy|^2 / sigma), base-frame velocity.
    tracking_ang_vel: exp(-(cmd_yaw - w_z)^2 / sigma).
    lin_vel_z: v_z^2.  ang_vel_xy: |w_xy|^2.  orientation: |g_xy|^2 (gravity in the base frame).
    base_height: (z - base_height_target)^2.
    torques: |tau|^2 (N m)^2.  action_rate: |a - a_prev|^2.  pose: |q_j - home|^2.
    stand_still: |q_j - home|_1 while the command is (near) zero.
    feet_air_time: sum over touch-downs of (air time - air_time_target), moving commands only.
    feet_phase: exp(-|z_feet - z_scheduled|^2 / 0.01) against the gait clock's swing heights.
    termination: 1 on a fall.
    """

    tracking_lin_vel: float = 1.0
    tracking_ang_vel: float = 0.5
    lin_vel_z: float = -0.5
    ang_vel_xy: float = -0.05
    orientation: float = -5.0
    base_height: float = 0.0
    torques: float = -2e-4
    action_rate: float = -0.01
    pose: float = -0.1
    stand_still: float = -0.5
    feet_air_time: float = 0.2
    feet_phase: float = 0.0
    termination: float = -1.0


@dataclasses.dataclass(frozen=True)
class EnvConfig:
    """A velocity-command task.

    Attributes:
      robot: robot name (``go1``, ``g1``).
      action_scale: joint-target offset per unit action (rad).
      commands: the command distribution.
      rewards: reward scales.
      tracking_sigma: width of the tracking kernels ((m/s)^2, (rad/s)^2).
      air_time_target: swing duration the air-time term rewards beyond (s).
      base_height_target: base height the base_height term aims at (m).
      gait_hz: gait clock frequency (Hz); 0: no clock in the observation (Go1).
      gait_duty: stance fraction of the clock's schedule.
      swing_height: scheduled swing height of the feet (m).
      init_joint_noise: std of the initial joint offsets (rad).
      init_height: added to the home pose's base height at reset (m).
      friction_min, friction_max: each episode's ground friction is the model's scaled by a
        factor drawn uniformly in this range at reset (:func:`with_ground`: the sliding
        friction of every geom and contact pair, as the closed loop's low-friction scenario
        scales it); 1, 1: the model's own, no randomisation. A policy trained on one friction
        walks on a knife edge on another (G1 at 0.3 of it falls from 0.01 rad of smooth action
        noise, ``results/planning_diagnosis/README.md``).
      action_noise: std (rad) of Gaussian noise added to every joint target in every control
        period while training (0: none): the policy learns to walk while its actions are
        perturbed, as a planner sampling around it (or an actuator) perturbs them.
      softness_min, softness_max: each episode's ground contact time constant (``solref[0]`` of
        every geom and contact pair) is the model's scaled by a factor drawn uniformly in this
        range at reset (:func:`with_ground`, as the closed loop's soft scenario scales it, 4
        there); 1, 1: the model's own. The G1 slope policy (slopes and friction randomised, the
        ground always hard) falls on the soft scenario in one episode in five from the GPU's
        float rounding alone, where the first policy stands
        (``results/planning_diagnosis/slope_policies/g1_soft_64_{slope,first}.md``).
      tilt_max_deg: each episode's ground slope is drawn uniformly in [0, this] degrees, uphill
        in a random direction, and built up linearly over the first ``tilt_s`` seconds (gravity
        tilted under the level floor, as the closed loop's ``tilt`` scenario does, so that a
        humanoid starts upright); the policy senses the tilted gravity (:func:`base_signals`).
        0: level ground.
      tilt_min_deg: the least slope drawn (degrees, <= ``tilt_max_deg``): a fine-tune that
        should spend its episodes on steep ground draws them in [this, ``tilt_max_deg``]. 0:
        from level.
      tilt_heading_deg: the uphill direction is drawn uniformly within this many degrees of the
        robot's forward direction at the start (its drawn heading); 180: any direction.
        Smaller: more of the episodes walk up the slope, as a robot sent uphill does (the
        commands stay drawn as before, so the robot still turns off the fall line).
      tilt_s: seconds over which an episode's slope builds up.
      tilt_friction_margin: with both the slope and the friction randomised, > 0 draws each
        episode's slope in [0, min(tilt_max_deg, atan(margin * mu))] instead (its least, too,
        no more than that bound), ``mu`` the feet's
        friction coefficient on the floor (:func:`foot_friction`) times the episode's friction
        factor: a slope steeper than ``atan(mu)`` is one no stance can hold, and 20-40% of the
        slope training's episodes fell with the two drawn apart (session 47). 0: drawn apart.
      sensor_noise: the policy observes the state through a real robot's sensors,
        :class:`stride_jax.sim.sensors.SensorNoise` scaled by this factor (1: a well-instrumented
        robot's), a fresh draw every control period (:func:`stride_jax.sim.sensors.measure`, what
        ``stride closed-loop --sensor-noise`` gives the controller); the world, rewards and
        terminations keep the true state. 0: the exact state.
      payload_max: each episode's robot carries a load drawn uniformly in [0, this] times its
        own mass, strapped on ``payload_body`` (:func:`with_payload`: the body's mass and
        rotational inertia scaled, its centre of mass kept, as the closed loop's ``payload``
        scenario loads it); the policy is not told. 0: no load. A G1 trained unloaded falls
        with +50% on its torso (``results/closed_loop/payload_g1_cpu/``).
      payload_body: the body that carries it, by name ("": the base body; a humanoid carries a
        backpack on its torso, ``torso_link``); a name the robot lacks fails when the
        environment is made, listing its bodies.
    """

    robot: str = "go1"
    action_scale: float = 0.3
    commands: Commands = Commands()
    rewards: RewardScales = RewardScales()
    tracking_sigma: float = 0.25
    air_time_target: float = 0.1
    base_height_target: float = 0.3
    gait_hz: float = 0.0
    gait_duty: float = 0.5
    swing_height: float = 0.08
    init_joint_noise: float = 0.1
    init_height: float = 0.02
    friction_min: float = 1.0
    friction_max: float = 1.0
    action_noise: float = 0.0
    softness_min: float = 1.0
    softness_max: float = 1.0
    tilt_max_deg: float = 0.0
    tilt_min_deg: float = 0.0
    tilt_heading_deg: float = 180.0
    tilt_s: float = 2.0
    tilt_friction_margin: float = 0.0
    sensor_noise: float = 0.0
    payload_max: float = 0.0
    payload_body: str = ""

    @property
    def randomises_friction(self) -> bool:
        return (self.friction_min, self.friction_max) != (1.0, 1.0)

    @property
    def randomises_softness(self) -> bool:
        return (self.softness_min, self.softness_max) != (1.0, 1.0)

    @property
    def randomises_tilt(self) -> bool:
        return self.tilt_max_deg > 0

    @property
    def randomises_payload(self) -> bool:
        return self.payload_max > 0

    def __post_init__(self):
        if not 0 < self.friction_min <= self.friction_max:
            raise ValueError(f"friction_min={self.friction_min}, friction_max={self.friction_max}: "
                             "need 0 < friction_min <= friction_max (factors on the model's friction)")
        if not 0 < self.softness_min <= self.softness_max:
            raise ValueError(f"softness_min={self.softness_min}, softness_max={self.softness_max}: "
                             "need 0 < softness_min <= softness_max (factors on the model's "
                             "contact time constant)")
        if self.action_noise < 0:
            raise ValueError(f"action_noise={self.action_noise} must be >= 0 (rad)")
        if not 0 <= self.tilt_max_deg < 90:
            raise ValueError(f"tilt_max_deg={self.tilt_max_deg} must be in [0, 90) (degrees)")
        if not 0 <= self.tilt_min_deg <= self.tilt_max_deg:
            raise ValueError(f"tilt_min_deg={self.tilt_min_deg} must be in [0, tilt_max_deg="
                             f"{self.tilt_max_deg}] (degrees)")
        if not 0 <= self.tilt_heading_deg <= 180:
            raise ValueError(f"tilt_heading_deg={self.tilt_heading_deg} must be in [0, 180] "
                             "(degrees either side of the start's forward direction)")
        if self.tilt_heading_deg != 180 and not self.tilt_max_deg:
            raise ValueError(f"tilt_heading_deg={self.tilt_heading_deg} turns the uphill of no "
                             "slope (tilt_max_deg=0)")
        if self.tilt_s <= 0:
            raise ValueError(f"tilt_s={self.tilt_s} must be > 0 (s)")
        if not self.tilt_friction_margin >= 0:
            raise ValueError(f"tilt_friction_margin={self.tilt_friction_margin} must be >= 0")
        if not (np.isfinite(self.sensor_noise) and self.sensor_noise >= 0):
            raise ValueError(f"sensor_noise={self.sensor_noise} must be a finite number >= 0 (a "
                             "factor on SensorNoise's defaults; 0: the exact state)")
        if not (np.isfinite(self.payload_max) and self.payload_max >= 0):
            raise ValueError(f"payload_max={self.payload_max} must be a finite number >= 0 (a "
                             "fraction of the robot's mass; 0: no load)")
        if self.payload_body and not self.payload_max:
            raise ValueError(f"payload_body={self.payload_body!r} names a body for no payload "
                             "(payload_max=0)")
        if self.action_scale <= 0:
            raise ValueError(f"action_scale={self.action_scale} must be > 0")
        if self.tracking_sigma <= 0:
            raise ValueError(f"tracking_sigma={self.tracking_sigma} must be > 0")
        c = self.commands
        for name in ("forward", "lateral", "yaw"):
            lo, hi = getattr(c, name)
            if hi < lo:
                raise ValueError(f"commands.{name}: upper bound {hi} below lower bound {lo}")
        if not 0 <= c.zero_prob <= 1 or c.resample_s <= 0:
            raise ValueError("commands: zero_prob must be in [0, 1] and resample_s > 0")


PRESETS = {
    "go1": EnvConfig(),
    "g1": EnvConfig(
        robot="g1", action_scale=0.3,
        commands=Commands(forward=(0.0, 1.0), lateral=(-0.3, 0.3), yaw=(-0.5, 0.5)),
        rewards=RewardScales(tracking_lin_vel=1.0, tracking_ang_vel=0.75, lin_vel_z=-0.5,
                             ang_vel_xy=-0.15, orientation=-2.0, base_height=-10.0, torques=-1e-5,
                             action_rate=-0.01, pose=-0.5, stand_still=-0.5, feet_air_time=0.0,
                             feet_phase=1.0, termination=-1.0),
        base_height_target=0.75, gait_hz=1.25, gait_duty=0.5, swing_height=0.08,
        init_joint_noise=0.05, init_height=0.0),
}


# The EnvConfig fields of the domain randomisation (`stride ppo`'s flags of the same names).
RANDOMISATION = ("friction_min", "friction_max", "action_noise", "softness_min", "softness_max",
                 "tilt_max_deg", "tilt_min_deg", "tilt_heading_deg", "tilt_friction_margin",
                 "sensor_noise", "payload_max", "payload_body")


def config(robot: str, **overrides) -> EnvConfig:
    """The preset task of ``robot`` with fields replaced by ``overrides``."""
    if robot not in PRESETS:
        raise ValueError(f"no environment for robot {robot!r}; available: {', '.join(PRESETS)}")
    return dataclasses.replace(PRESETS[robot], **overrides)


# ---------------------------------------------------------------------------------------------
# Pure functions of one state.


def rotate_inv(quat: jax.Array, v: jax.Array) -> jax.Array:
    """``R(quat)^T v``: a world vector in the frame of unit quaternion ``quat`` (w x y z)."""
    quat = quat / jnp.maximum(jnp.linalg.norm(quat), 1e-9)
    w, u = quat[0], -quat[1:]
    t = 2.0 * jnp.cross(u, v)
    return v + w * t + jnp.cross(u, t)


def base_signals(q: jax.Array, qd: jax.Array, gravity: jax.Array | None = None
                 ) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Base-frame linear velocity ``[3]`` (m/s), angular velocity ``[3]`` (rad/s), and gravity
    direction ``[3]`` (unit) of a floating-base state (MJX: world linear, body angular).
    ``gravity``: the world's gravity direction ``[3]`` (unit) as an IMU senses it; default world
    down, ``-z``. A slope emulated by tilting gravity under a level floor (the closed loop's
    ``slope``, ``tilt``) must pass its gravity: a real robot's IMU on a real slope reads the
    slope, and world down would hide it."""
    quat = q[3:7]
    down = jnp.asarray(WORLD_DOWN if gravity is None else gravity, q.dtype)
    return rotate_inv(quat, qd[0:3]), qd[3:6], rotate_inv(quat, down)


# a command above this norm moves the robot (the stand-still and air-time terms switch on it)
MOVING = 0.1


def obs_layout(cfg: EnvConfig, nu: int) -> dict[str, slice]:
    """Where each part of :func:`observe`'s vector lies: ``v``, ``w`` (base-frame linear and
    angular velocity), ``gravity``, ``joint_pos``, ``joint_vel``, ``command`` and, with a gait
    clock, ``clock``."""
    sizes = [("v", 3), ("w", 3), ("gravity", 3), ("joint_pos", nu), ("joint_vel", nu),
             ("command", 3)] + ([("clock", 2)] if cfg.gait_hz > 0 else [])
    out, at = {}, 0
    for name, n in sizes:
        out[name] = slice(at, at + n)
        at += n
    return out


def obs_layout_of_size(cfg: EnvConfig, size: int, what: str) -> dict[str, slice]:
    """:func:`obs_layout` of the task's observations of ``size`` entries (the joints' count
    read from it); a ValueError naming ``what`` where no joint count gives that size."""
    nu = (size - obs_size(cfg, 0)) // 2
    if nu < 1 or obs_size(cfg, nu) != size:
        raise ValueError(f"{what}: observations of size {size} are not the velocity task's "
                         f"(stride_jax.control.envs.observe; gait clock: {cfg.gait_hz > 0})")
    return obs_layout(cfg, nu)


def observe(cfg: EnvConfig, home: jax.Array, q: jax.Array, qd: jax.Array, command: jax.Array,
            clock: jax.Array | None = None, gravity: jax.Array | None = None) -> jax.Array:
    """The policy's observation ``[obs_size]`` of state ``(q [nq], qd [nv])`` under ``command``
    ``[3]``, laid out as :func:`obs_layout` says; ``clock`` (cycles) is required when
    ``cfg.gait_hz > 0``. ``home`` ``[nu]``; ``gravity``: the sensed gravity direction
    (:func:`base_signals`)."""
    v, w, g = base_signals(q, qd, gravity)
    parts = [v, w, g, q[7:] - home, qd[6:], command]
    if cfg.gait_hz > 0:
        if clock is None:
            raise ValueError(f"the {cfg.robot} task observes a gait clock: pass clock")
        parts.append(jnp.stack([jnp.cos(2 * jnp.pi * clock), jnp.sin(2 * jnp.pi * clock)]))
    obs = jnp.concatenate(parts)
    return jnp.where(jnp.isfinite(obs), obs, 0.0)  # a diverged world must not poison statistics


def obs_size(cfg: EnvConfig, nu: int) -> int:
    return max(s.stop for s in obs_layout(cfg, nu).values())


def tracking_terms(cfg: EnvConfig, command: jax.Array, v: jax.Array, w: jax.Array
                   ) -> dict[str, jax.Array]:
    """The velocity-tracking reward terms (unscaled) of base-frame velocities ``v``, ``w``
    (``[..., 3]``) under ``command`` (``[..., 3]``)."""
    sig = cfg.tracking_sigma
    return {"tracking_lin_vel": jnp.exp(-jnp.sum((command[..., :2] - v[..., :2]) ** 2, -1) / sig),
            "tracking_ang_vel": jnp.exp(-(command[..., 2] - w[..., 2]) ** 2 / sig)}


def state_terms(cfg: EnvConfig, home: jax.Array, q: jax.Array, qd: jax.Array,
                command: jax.Array, torque: jax.Array, fallen: jax.Array,
                gravity: jax.Array | None = None) -> dict[str, jax.Array]:
    """The reward terms that depend on the state, command and joint torques ``[nu]`` (N m) only
    (unscaled). A planner scores its rollouts with the same functions as the environment.
    ``gravity``: the sensed gravity direction (:func:`base_signals`; the orientation term keeps
    the base upright against it)."""
    v, w, g = base_signals(q, qd, gravity)
    moving = jnp.linalg.norm(command) > MOVING
    return {
        **tracking_terms(cfg, command, v, w),
        "lin_vel_z": v[2] ** 2,
        "ang_vel_xy": jnp.sum(w[:2] ** 2),
        "orientation": jnp.sum(g[:2] ** 2),
        "base_height": (q[2] - cfg.base_height_target) ** 2,
        "torques": jnp.sum(torque ** 2),
        "pose": jnp.sum((q[7:] - home) ** 2),
        "stand_still": jnp.where(moving, 0.0, jnp.sum(jnp.abs(q[7:] - home))),
        "termination": fallen.astype(jnp.float32),
    }


def total_reward(cfg: EnvConfig, terms: dict[str, jax.Array], dt: float) -> tuple[jax.Array, dict]:
    """``max(0, dt * sum scale_i term_i)`` and each term's scaled contribution."""
    scales = dataclasses.asdict(cfg.rewards)
    unknown = set(terms) - set(scales)
    if unknown:
        raise ValueError(f"reward terms without a scale: {sorted(unknown)}")
    parts = {k: dt * scales[k] * v for k, v in terms.items() if scales[k] != 0}
    total = sum(parts.values()) if parts else jnp.zeros(())
    return jnp.maximum(total, 0.0), parts


def sample_command(c: Commands, key: jax.Array) -> jax.Array:
    """One command ``[3]`` (vx, vy in m/s, yaw rate in rad/s)."""
    k_cmd, k_zero = jax.random.split(key)
    lo, hi = c.bounds()
    cmd = jax.random.uniform(k_cmd, (3,), minval=lo, maxval=hi)
    return jnp.where(jax.random.bernoulli(k_zero, c.zero_prob), 0.0, cmd)


def command_schedules(c: Commands, key: jax.Array, worlds: int, pieces: int, change_s: float
                      ) -> tuple[jax.Array, jax.Array]:
    """``(starts [P], values [W, P, 3])``: ``worlds`` command schedules of ``pieces`` draws of
    :func:`sample_command` each, a new one every ``change_s`` seconds (a closed-loop episode's
    ``(starts, values)``, :func:`stride_jax.control.episode.run_episode`)."""
    starts = jnp.arange(pieces, dtype=jnp.float32) * change_s
    values = jax.vmap(lambda k: jax.vmap(lambda kk: sample_command(c, kk))(
        jax.random.split(k, pieces)))(jax.random.split(key, worlds))
    return starts, values


# ---------------------------------------------------------------------------------------------
# The environment.


class VelocityEnv(brax_base.Env):
    """A velocity-command MJX environment for one world (Brax ``Env``).

    ``mj_model`` replaces the robot's nominal ``MjModel`` (a slope, other ground) while keeping its
    definition; the contact layout is read from the model used.
    """

    def __init__(self, cfg: EnvConfig, mj_model: mujoco.MjModel | None = None):
        self.cfg = cfg
        self.sm = sim_model.load(cfg.robot)
        if not self.sm.robot.floating_base or self.sm.robot.kp is None:
            raise ValueError(f"robot {cfg.robot!r}: velocity tasks need a floating base and "
                             "position servos")
        self.mj = mj_model if mj_model is not None else self.sm.mj
        self.mx = mjx.put_model(self.mj)
        self.slots = contact_slots(self.mx)
        info = self.sm.info
        self.home = jnp.asarray(info.qpos0[7:])
        self.qpos0 = jnp.asarray(info.qpos0).at[2].add(cfg.init_height)
        self.lo, self.hi = jnp.asarray(info.ctrl_lo), jnp.asarray(info.ctrl_hi)
        self.dt = float(info.ctrl_dt)
        self.nu = int(info.nu)
        self.resample_steps = max(1, int(round(cfg.commands.resample_s / self.dt)))
        d = mujoco.MjData(self.sm.mj)
        d.qpos[:] = info.qpos0
        mujoco.mj_kinematics(self.sm.mj, d)
        self.foot_z0 = jnp.asarray(d.site_xpos[self.sm.foot_sites, 2], jnp.float32)
        self.sensor_spec = (sensors.SensorNoise().scaled(cfg.sensor_noise) if cfg.sensor_noise
                            else None)
        # the feet's friction on the floor, where it bounds the slopes drawn
        self.foot_mu = foot_friction(self.sm, self.mj) if cfg.tilt_friction_margin else None
        # where a drawn payload sits, and the mass its fraction is of
        self.payload_body_id = sim_model.body_id(self.sm, cfg.payload_body, "payload_body")
        if cfg.randomises_payload:
            randomize.check_payload_body(self.mj.body_mass, self.payload_body_id,
                                         f"payload_body {cfg.payload_body or 'the base'!r}")
        self.robot_mass = float(self.mj.body_mass.sum())

    # -- Brax Env API -------------------------------------------------------------------------
    @property
    def observation_size(self) -> int:
        return obs_size(self.cfg, self.nu)

    @property
    def action_size(self) -> int:
        return self.nu

    @property
    def backend(self) -> str:
        return "mjx"

    def reset(self, rng: jax.Array) -> brax_base.State:
        """A fresh world: home pose with joint noise, a random heading, a drawn command (and,
        where the config randomises it, the episode's ground friction factor)."""
        rng, k_joint, k_yaw, k_cmd, k_clock = jax.random.split(rng, 5)
        yaw = jax.random.uniform(k_yaw, minval=-jnp.pi, maxval=jnp.pi)
        qpos = self.qpos0.at[3:7].set(jnp.array([jnp.cos(yaw / 2), 0, 0, jnp.sin(yaw / 2)]))
        qpos = qpos.at[7:].add(self.cfg.init_joint_noise * jax.random.normal(k_joint, (self.nu,)))
        # No forward pass: the next mjx.step starts with one, and the observation needs q, qd only.
        d = mjx.make_data(self.mx).replace(qpos=qpos, ctrl=jnp.clip(qpos[7:], self.lo, self.hi))
        command = sample_command(self.cfg.commands, k_cmd)
        clock = jax.random.uniform(k_clock) if self.cfg.gait_hz > 0 else jnp.zeros(())
        nf = self.sm.nfeet
        # (keys folded from one already drawn: without randomisation the streams stay as before)
        friction = (jax.random.uniform(jax.random.fold_in(k_clock, 1), minval=self.cfg.friction_min,
                                       maxval=self.cfg.friction_max)
                    if self.cfg.randomises_friction else jnp.ones(()))
        softness = (jax.random.uniform(jax.random.fold_in(k_clock, 4), minval=self.cfg.softness_min,
                                       maxval=self.cfg.softness_max)
                    if self.cfg.randomises_softness else jnp.ones(()))
        payload = (self.robot_mass * jax.random.uniform(
            jax.random.fold_in(k_clock, 5), maxval=self.cfg.payload_max)
                   if self.cfg.randomises_payload else jnp.zeros(()))
        tilt = jnp.zeros(2)  # (slope rad, uphill heading rad); level at t = 0 either way
        if self.cfg.randomises_tilt:
            steepest = jnp.deg2rad(self.cfg.tilt_max_deg)
            least = jnp.deg2rad(self.cfg.tilt_min_deg)
            if self.cfg.tilt_friction_margin:  # no steeper than the feet can hold
                holds = jnp.arctan(self.cfg.tilt_friction_margin * self.foot_mu * friction)
                steepest, least = jnp.minimum(steepest, holds), jnp.minimum(least, holds)
            spread = jnp.deg2rad(self.cfg.tilt_heading_deg)
            uphill = jax.random.uniform(jax.random.fold_in(k_clock, 3), minval=-spread,
                                        maxval=spread)
            if self.cfg.tilt_heading_deg < 180:  # about the start's heading (any: drawn apart)
                uphill = jnp.mod(uphill + yaw + jnp.pi, 2 * jnp.pi) - jnp.pi
            tilt = jnp.stack([
                least + (steepest - least) * jax.random.uniform(jax.random.fold_in(k_clock, 2)),
                uphill])
        info = {"rng": rng, "command": command, "last_action": jnp.zeros(self.nu),
                "air_time": jnp.zeros(nf), "last_contact": jnp.ones(nf, bool),
                "clock": clock, "t": jnp.zeros((), jnp.int32), "friction": friction,
                "softness": softness, "tilt": tilt, "payload": payload}
        obs = observe(self.cfg, self.home, *self._sensed(d.qpos, d.qvel, k_clock), command, clock)
        _, parts = total_reward(self.cfg, self._terms_zero(), self.dt)
        metrics = {f"reward/{k}": jnp.zeros(()) for k in parts}
        metrics["fallen"] = jnp.zeros(())
        return brax_base.State(d, obs, jnp.zeros(()), jnp.zeros(()), metrics, info)

    def step(self, state: brax_base.State, action: jax.Array) -> brax_base.State:
        """One control period under ``action`` ``[nu]`` in [-1, 1]."""
        cfg, info = self.cfg, dict(state.info)
        action = jnp.clip(action, -1.0, 1.0)
        target = self.home + cfg.action_scale * action
        rng, k_cmd = jax.random.split(info["rng"])
        if cfg.action_noise:
            target = target + cfg.action_noise * jax.random.normal(jax.random.fold_in(k_cmd, 1),
                                                                   target.shape)
        ctrl = jnp.clip(target, self.lo, self.hi)
        mx = with_ground(self.mx, info["friction"] if cfg.randomises_friction else None,
                         info["softness"] if cfg.randomises_softness else None)
        if cfg.randomises_payload:
            mx = with_payload(mx, self.payload_body_id, info["payload"])
        up = None  # the sensed gravity after the step (world down on level ground)
        if cfg.randomises_tilt:  # the slope built up over tilt_s, as the ``tilt`` scenario's
            ramp = jnp.stack([info["tilt"][0], jnp.asarray(cfg.tilt_s, info["tilt"].dtype)])

            def gravity(step):
                return scenarios.gravity_at(ramp, step * self.dt, self.mx.opt.gravity,
                                            info["tilt"][1])
            mx = mx.replace(opt=mx.opt.replace(gravity=gravity(info["t"])))
            g_next = gravity(info["t"] + 1)
            up = g_next / jnp.linalg.norm(g_next)
        d = physics_step(mx, self.sm.n_substeps, state.pipeline_state, ctrl)
        q, qd = d.qpos, d.qvel
        finite = jnp.all(jnp.isfinite(q)) & jnp.all(jnp.isfinite(qd))
        fallen = rollout_mjx.fallen(self.sm, q) | ~finite

        contact = foot_contact(self.sm, self.slots, d)
        first = contact & ~info["last_contact"]
        air = info["air_time"] + self.dt
        clock = jnp.mod(info["clock"] + cfg.gait_hz * self.dt, 1.0)
        command = info["command"]
        terms = state_terms(cfg, self.home, q, qd, command, d.actuator_force, fallen, up)
        moving = jnp.linalg.norm(command) > MOVING
        terms["action_rate"] = jnp.sum((action - info["last_action"]) ** 2)
        terms["feet_air_time"] = jnp.where(
            moving, jnp.sum((air - cfg.air_time_target) * first), 0.0)
        phases = gait_lib.leg_phases(clock, jnp.arange(self.sm.nfeet) / self.sm.nfeet)
        z_ref = self.foot_z0 + gait_lib.swing_height(phases, cfg.gait_duty, cfg.swing_height)
        z = d.site_xpos[self.sm.foot_sites, 2]
        terms["feet_phase"] = jnp.where(moving, jnp.exp(-jnp.sum((z - z_ref) ** 2) / 0.01), 0.0)
        reward, parts = total_reward(cfg, terms, self.dt)
        reward = jnp.where(finite, reward, 0.0)

        t = info["t"] + 1
        resample = (t % self.resample_steps) == 0
        command = jnp.where(resample, sample_command(cfg.commands, k_cmd), command)
        info.update(rng=rng, command=command, last_action=action,
                    air_time=jnp.where(contact, 0.0, air), last_contact=contact, clock=clock, t=t)
        obs = observe(cfg, self.home, *self._sensed(q, qd, k_cmd), command, clock, up)
        metrics = {f"reward/{k}": jnp.where(finite, v, 0.0) for k, v in parts.items()}
        metrics["fallen"] = fallen.astype(jnp.float32)
        return state.replace(pipeline_state=d, obs=obs, reward=reward,
                             done=fallen.astype(jnp.float32), metrics=metrics, info=info)

    def _sensed(self, q: jax.Array, qd: jax.Array, key: jax.Array) -> tuple[jax.Array, jax.Array]:
        """``(q, qd)`` as the policy observes them: through the sensors where ``sensor_noise``
        is set (a key folded from one already drawn: without it the streams stay as before)."""
        if self.sensor_spec is None:
            return q, qd
        return sensors.measure(self.sensor_spec, q, qd, jax.random.fold_in(key, 5), floating_base=True)

    def _terms_zero(self) -> dict:
        names = ("tracking_lin_vel", "tracking_ang_vel", "lin_vel_z", "ang_vel_xy", "orientation",
                 "base_height", "torques", "pose", "stand_still", "termination", "action_rate",
                 "feet_air_time", "feet_phase")
        return {k: jnp.zeros(()) for k in names}

    # -- helpers for planners and policies ----------------------------------------------------
    def observation_fn(self):
        """``obs(q, qd, command, clock=None) -> [obs_size]``, the environment's own."""
        return functools.partial(observe, self.cfg, self.home)

    def ctrl_from_action(self, action: jax.Array) -> jax.Array:
        """Joint targets ``[nu]`` (rad) of a normalised action ``[nu]``."""
        return jnp.clip(self.home + self.cfg.action_scale * jnp.clip(action, -1, 1),
                        self.lo, self.hi)


def foot_friction(sm: sim_model.SimModel, m: mujoco.MjModel) -> float:
    """The least sliding friction coefficient among the feet's contacts with the ground in the
    home pose, pressed 1 cm into the floor (MuJoCo's combination of the two geoms', or an
    explicit pair's): the slope a stance can hold is ``atan`` of it."""
    d = mujoco.MjData(m)
    d.qpos[:] = sm.info.qpos0
    d.qpos[2] -= 0.01
    mujoco.mj_forward(m, d)
    con = d.contact[:d.ncon]
    feet = (sm.geom_foot[con.geom1] >= 0) | (sm.geom_foot[con.geom2] >= 0) if d.ncon else []
    if not np.any(feet):
        raise ValueError(f"robot {sm.robot.name!r}: no foot touches the ground in the home pose "
                         "pressed 1 cm down (no friction to bound the slope by)")
    return float(con.friction[feet, 0].min())


def with_ground(mx: mjx.Model, friction: jax.Array | None = None,
                softness: jax.Array | None = None) -> mjx.Model:
    """``mx`` on other ground, on the device (the factors may be traced: one per world under
    ``vmap``; ``None`` leaves that property the model's own):

    - ``friction``: the sliding friction of every geom and of every explicit contact pair (G1's
      feet meet the floor through pairs, which ignore the geoms' friction) scaled by it
      (:func:`stride_jax.sim.randomize.sliding_friction`, as the low-friction scenario scales an
      ``MjModel``);
    - ``softness``: the contact time constant of every geom and pair scaled by it (> 1: softer;
      :func:`stride_jax.sim.randomize.contact_softness`, as the soft scenario does)."""
    if friction is not None:
        geom, pair = randomize.sliding_friction(mx.geom_friction, mx.pair_friction,
                                                jnp.asarray(friction, mx.geom_friction.dtype))
        mx = mx.replace(geom_friction=geom, pair_friction=pair)
    if softness is not None:
        geom, pair = randomize.contact_softness(mx.geom_solref, mx.pair_solref,
                                                jnp.asarray(softness, mx.geom_solref.dtype))
        mx = mx.replace(geom_solref=geom, pair_solref=pair)
    return mx


def with_payload(mx: mjx.Model, body: int, kg: jax.Array) -> mjx.Model:
    """``mx`` with ``kg`` (may be traced: one per world under ``vmap``) strapped on body
    ``body`` (:func:`stride_jax.sim.randomize.payload_fields`; derived constants such as
    ``body_invweight0`` kept, as the hidden randomisation keeps them)."""
    mass, inertia = randomize.payload_fields(mx.body_mass, mx.body_inertia, body,
                                             jnp.asarray(kg, mx.body_mass.dtype))
    return mx.replace(body_mass=mass, body_inertia=inertia)


def physics_step(mx: mjx.Model, n_substeps: int, d: mjx.Data, ctrl: jax.Array) -> mjx.Data:
    """Holds ``ctrl`` for ``n_substeps`` MJX steps (full float32 products, as the data's:
    ``rollout_mjx.PRECISION``)."""
    with jax.default_matmul_precision(rollout_mjx.PRECISION):
        d = d.replace(ctrl=ctrl)
        return jax.lax.fori_loop(0, n_substeps, lambda _, dd: mjx.step(mx, dd), d)


def mjx_step_fn(n_substeps: int, mx: mjx.Model) -> Callable:
    """``step(q, qd, ctrl, key) -> (q', qd')``: one control period of an MJX model, the
    planner's dynamics when it plans through the simulator (the oracle; ``key`` is unused, and
    so is a gravity direction ``down``: the model has its own world's gravity)."""
    def step(q, qd, ctrl, key, down=None):
        d = physics_step(mx, n_substeps, mjx.make_data(mx).replace(qpos=q, qvel=qd), ctrl)
        return d.qpos, d.qvel
    return step


def contact_slots(mx: mjx.Model) -> tuple[np.ndarray, np.ndarray]:
    """Static ``(efc_address [ncon], rows [ncon])`` of MJX's contact slots (pyramidal cones:
    ``2 (condim - 1)`` rows each), read without a forward pass."""
    con = mjx.make_data(mx)._impl.contact
    dim = np.asarray(con.dim)
    return np.asarray(con.efc_address), np.where(dim == 1, 1, 2 * (dim - 1))


def foot_contact(sm: sim_model.SimModel, slots: tuple[np.ndarray, np.ndarray],
                 d: mjx.Data) -> jax.Array:
    """Whether each foot carries a positive normal force; bool ``[nfeet]``. A slot's normal force
    is the sum of its pyramid-edge forces (as :func:`stride_jax.sim.record.from_mjx` sums them);
    the foot owning a slot is read from the slot's geoms at run time, so any floor works."""
    adr, rows = slots
    if len(adr) == 0:
        return jnp.zeros(sm.nfeet, bool)
    efc = d._impl.efc_force
    slot_force = jnp.stack([efc[a:a + n].sum() for a, n in zip(adr, rows)])
    owner = jnp.max(jnp.asarray(sm.geom_foot)[d._impl.contact.geom], axis=-1)  # [ncon]
    force = jax.ops.segment_sum(jnp.where(owner >= 0, slot_force, 0.0), jnp.maximum(owner, 0),
                                num_segments=sm.nfeet)
    return force > 1e-3


def make(robot: str, **overrides) -> VelocityEnv:
    """The velocity-command environment of ``robot`` (``go1`` or ``g1``)."""
    return VelocityEnv(config(robot, **overrides))
