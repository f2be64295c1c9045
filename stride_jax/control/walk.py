"""Walking data: a trained PPO policy as the data-collecting explorer.

The paper's data are locomotion: the robots walk under velocity commands. Our robots' own explorers
(a gait library for the Go1, balance and stepping in place for the G1) cover states near their
references; :class:`PolicyExplorer` instead drives the robot with a trained velocity-command policy
(``stride ppo``, ``results/policies/``), commands drawn over the policy's own range and re-drawn
every ``resample_s`` seconds, with Gaussian noise on its actions so that the data also show how the
robot responds off the policy's choices. It follows the :class:`~stride_jax.robots.Explorer`
protocol (pure JAX, one world, everything random from the episode key and the step), so both
simulation backends issue the same controls from the same states.

    stride data --robot g1 --policy results/policies/ppo_g1 --action-noise 0.3 --out data/g1-walk
"""

from __future__ import annotations

import math
import pathlib
from typing import NamedTuple

import jax
import jax.numpy as jnp

from stride_jax.control import envs, ppo
from stride_jax.robots import ModelInfo


class WalkParams(NamedTuple):
    key: jax.Array
    commands: jax.Array  # [S, 3] the command of each resampling segment (vx, vy, yaw rate)
    noise: jax.Array  # std of the Gaussian noise on the policy's actions (action units)
    clock0: jax.Array  # gait clock at the start (cycles; robots with a clock)
    yaw: jax.Array  # initial heading (rad)
    joint_noise0: jax.Array  # [nu] initial joint offsets (rad)


class PolicyExplorer:
    """Velocity commands tracked by a trained policy, with noise on its actions. It senses the
    world's gravity direction as the policy's IMU would (``senses_gravity``): on sloped data it
    sees the slope, as in the closed loop's sensed slope scenarios.

    Args:
      run: a PPO run folder (``config.json`` and a checkpoint).
      action_noise: per-episode noise std is uniform in ``[0, action_noise]`` (in the policy's
        action units: ``action_noise * action_scale`` rad on the joint targets).
      max_seconds: the longest episode the commands are drawn for (s).
    """

    senses_gravity = True  # act(..., gravity=): the backends pass each world's on sloped data

    def __init__(self, run: str | pathlib.Path, action_noise: float = 0.3,
                 max_seconds: float = 60.0):
        if action_noise < 0:
            raise ValueError(f"action_noise={action_noise} must be >= 0")
        self.run = str(run)
        self.policy, _, self.cfg = ppo.load_policy(run, deterministic=True)
        self.action_noise = float(action_noise)
        self.segments = max(1, math.ceil(max_seconds / self.cfg.commands.resample_s))

    def __repr__(self) -> str:
        return f"PolicyExplorer({self.run!r}, action_noise={self.action_noise})"

    def sample(self, key: jax.Array, info: ModelInfo) -> WalkParams:
        k_key, k_cmd, k_noise, k_clock, k_yaw, k_joint = jax.random.split(key, 6)
        commands = jax.vmap(lambda k: envs.sample_command(self.cfg.commands, k))(
            jax.random.split(k_cmd, self.segments))
        return WalkParams(
            key=k_key, commands=commands,
            noise=jax.random.uniform(k_noise, maxval=self.action_noise),
            clock0=jax.random.uniform(k_clock),
            yaw=jax.random.uniform(k_yaw, minval=-jnp.pi, maxval=jnp.pi),
            joint_noise0=self.cfg.init_joint_noise * jax.random.normal(k_joint, (info.nu,)))

    def reset(self, params: WalkParams, info: ModelInfo):
        """The environment's own reset: home pose, a random heading, joint noise, at rest."""
        half = params.yaw / 2
        qpos = (jnp.asarray(info.qpos0).at[2].add(self.cfg.init_height)
                .at[3:7].set(jnp.stack([jnp.cos(half), 0.0, 0.0, jnp.sin(half)]))
                .at[7:].add(params.joint_noise0))
        return qpos, jnp.zeros(info.nv)

    def command(self, params: WalkParams, info: ModelInfo, step) -> jax.Array:
        """The command ``[3]`` at control step ``step``."""
        per = max(1, round(self.cfg.commands.resample_s / info.ctrl_dt))
        return params.commands[jnp.minimum(step // per, self.segments - 1)]

    def act(self, params: WalkParams, info: ModelInfo, step, qpos, qvel, gravity=None):
        """The policy's noisy action at ``(qpos, qvel)``; ``gravity``: the world's gravity
        direction ``[3]`` as its IMU senses it (default: world down)."""
        cfg = self.cfg
        clock = jnp.mod(params.clock0 + cfg.gait_hz * info.ctrl_dt * step, 1.0)
        home = jnp.asarray(info.qpos0[7:])
        obs = envs.observe(cfg, home, qpos, qvel, self.command(params, info, step), clock,
                           gravity)
        key = jax.random.fold_in(params.key, step)  # the deterministic policy draws nothing
        action = self.policy(obs, key) + params.noise * jax.random.normal(key, (info.nu,))
        ctrl = home + cfg.action_scale * jnp.clip(action, -1.0, 1.0)
        return jnp.clip(ctrl, info.ctrl_lo, info.ctrl_hi)
