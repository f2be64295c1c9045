"""Dataset generation: the config, its presets, and the job that writes a dataset folder."""

from __future__ import annotations

import dataclasses
import pathlib
import time

import jax
import mujoco
from tqdm import tqdm

from stride_jax import distributed
from stride_jax.distributed import DistributedConfig
from stride_jax.robots import Explorer, stochastic
from stride_jax.sim import dataset, model, rollout_cpu, rollout_mjx


@dataclasses.dataclass(frozen=True)
class DataConfig:
    """What ``stride data`` generates.

    Attributes:
      robot: pendulum, pendulum_bouncing, go1 or g1.
      backend: ``mjx`` (jit/vmap on any JAX device), ``cpu`` (threaded ``mujoco.rollout``), or
        ``auto``: mjx when an accelerator is present, cpu otherwise.
      episodes: number of episodes (worlds).
      seconds: episode length (s); 0 uses the robot's default.
      batch: worlds per jitted MJX call (0: all at once).
      seed: PRNG seed of randomisation, exploration and the split.
      randomized: apply the hidden randomisation.
      stochastic: a contact residual that is stochastic given the state: ground patches of
        varying friction and softness along the path, several pushes per episode
        (:func:`stride_jax.robots.stochastic`; implies ``randomized``).
      policy: a PPO run folder whose policy explores (walking under velocity commands,
        :class:`stride_jax.control.walk.PolicyExplorer`); empty: the robot's own explorer.
      action_noise: with ``policy``, the largest per-episode std of the noise on its actions.
      out: output folder; empty means ``data/<robot>``.
      distributed: several processes share the episodes (:mod:`stride_jax.distributed`).
    """

    robot: str = "pendulum"
    backend: str = "auto"
    episodes: int = 64
    seconds: float = 0.0
    batch: int = 0
    seed: int = 0
    randomized: bool = True
    stochastic: bool = False
    policy: str = ""
    action_noise: float = 0.3
    out: str = ""
    distributed: DistributedConfig = DistributedConfig()


PRESETS = {
    "tiny": dict(episodes=8, seconds=1.0),
    "default": {},
    "paper": dict(episodes=4096, backend="mjx", batch=1024),
}


def resolve_backend(backend: str) -> str:
    if backend == "auto":
        return "cpu" if jax.default_backend() == "cpu" else "mjx"
    if backend not in ("cpu", "mjx"):
        raise ValueError(f"unknown backend {backend!r}; use cpu, mjx or auto")
    return backend


def generate(cfg: DataConfig, explorer: Explorer | None = None) -> dataset.Dataset:
    """Simulates ``cfg`` and writes the dataset; shows progress; returns the saved dataset.

    ``explorer`` replaces the robot's own; it is required when ``cfg.policy`` is set (the command
    line builds the policy's explorer: :class:`stride_jax.control.walk.PolicyExplorer`).
    """
    distributed.initialize(cfg.distributed)
    sm = model.load(cfg.robot)
    if cfg.policy and explorer is None:
        raise ValueError(f"policy={cfg.policy!r}: pass its explorer, "
                         "stride_jax.control.walk.PolicyExplorer(cfg.policy, cfg.action_noise)")
    robot = sm.robot
    if cfg.stochastic:
        robot = dataclasses.replace(robot, randomization=stochastic(robot.randomization))
    if explorer is not None:
        robot = dataclasses.replace(robot, explorer=explorer)
    if robot is not sm.robot:
        sm = dataclasses.replace(sm, robot=robot)
    randomized = cfg.randomized or cfg.stochastic
    if cfg.episodes < 3:
        raise ValueError(f"episodes must be >= 3 (train/val/test split), got {cfg.episodes}")
    seconds = cfg.seconds or sm.robot.episode_s
    n_steps = max(1, int(round(seconds / sm.robot.ctrl_dt)))
    backend = resolve_backend(cfg.backend)
    key = jax.random.key(cfg.seed)
    part = distributed.share(cfg.episodes)  # all of them for a single process
    quiet = not distributed.is_main()
    t0 = time.perf_counter()
    if backend == "mjx":
        with tqdm(total=part.stop - part.start, desc=f"{cfg.robot} mjx", unit="episode",
                  disable=quiet) as bar:
            ep = rollout_mjx.collect(sm, key, cfg.episodes, n_steps, cfg.batch or None,
                                     randomized, bar.update, part)
    else:
        with tqdm(total=n_steps, desc=f"{cfg.robot} cpu", unit="step", disable=quiet) as bar:
            ep = rollout_cpu.collect(sm, key, cfg.episodes, n_steps, randomized,
                                     progress=bar.update, part=part)
    ep = distributed.gather(ep)  # every process's share, in episode order
    seconds_taken = time.perf_counter() - t0
    out = pathlib.Path(cfg.out or f"data/{cfg.robot}")
    if not distributed.is_main():
        distributed.barrier("dataset written")
        return dataset.load(out)
    meta = dict(
        robot_meta(sm), backend=backend, seed=cfg.seed,
        exploration=type(sm.robot.explorer).__name__,
        explorer=repr(explorer) if explorer is not None else None,
        randomization=dataclasses.asdict(sm.robot.randomization) if randomized else None,
        config=dataclasses.asdict(cfg), generation_seconds=seconds_taken,
    )
    ds = dataset.save(out, ep, meta)
    distributed.barrier("dataset written")
    return ds


def robot_meta(sm: model.SimModel) -> dict:
    """What a dynamics model needs to know about a robot (coordinates, servos, timing): the part
    of a dataset's ``meta.json`` that describes the robot rather than the data."""
    m = sm.mj
    return dict(
        robot=sm.robot.name, source=sm.robot.source, nq=m.nq, nv=m.nv,
        sim_dt=float(m.opt.timestep), ctrl_dt=sm.robot.ctrl_dt, n_substeps=sm.n_substeps,
        joints=list(sm.robot.joints), feet=[f.name for f in sm.robot.feet],
        floating_base=sm.robot.floating_base,
        kp=list(sm.robot.kp) if sm.robot.kp else None,
        kd=list(sm.robot.kd) if sm.robot.kd else None,
        actuator_force_range=m.actuator_forcerange.tolist(),
        act_dof=sm.act_dof.tolist(),
        periodic=[bool(m.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE and not m.jnt_limited[j])
                  for j in range(m.njnt) if m.jnt_type[j] != mujoco.mjtJoint.mjJNT_FREE],
        ctrl_range=m.actuator_ctrlrange.tolist(),
        total_mass=float(m.body_mass.sum()),
    )
