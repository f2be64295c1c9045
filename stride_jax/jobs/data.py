"""``stride data``: the config, its presets, and the job that simulates a robot and writes a
dataset folder (``arrays.npz``, ``meta.json`` and a summary plot).

The library parts it composes: the rollouts (:mod:`stride_jax.sim.rollout_cpu`,
:mod:`~stride_jax.sim.rollout_mjx`), the dataset format (:mod:`stride_jax.sim.dataset`) and the
robot's description (:func:`stride_jax.sim.model.robot_meta`).
"""

from __future__ import annotations

import dataclasses
import math
import pathlib
import time

import jax
from tqdm import tqdm

from stride_jax import distributed
from stride_jax.distributed import DistributedConfig
from stride_jax.robots import Explorer, stochastic
from stride_jax.sim import dataset, model, randomize, rollout_cpu, rollout_mjx


@dataclasses.dataclass(frozen=True)
class DataConfig:
    """What ``stride data`` generates.

    Attributes:
      robot: pendulum, pendulum_bouncing, go1 or g1.
      backend: ``mjx`` (jit/vmap on any JAX device), ``warp`` (MJX on MuJoCo Warp's kernels:
        CUDA or CPU, needs ``warp-lang``; not with rough ground), ``cpu`` (threaded
        ``mujoco.rollout``), or ``auto``: mjx when an accelerator is present, cpu otherwise.
      episodes: number of episodes (worlds).
      seconds: episode length (s); 0 uses the robot's default.
      batch: worlds simulated at once (0: all), split over the process's devices.
      split: how several devices of one process share the worlds (MJX backends):
        ``threads``, each device its own share of the episodes, its own program and a host
        thread dispatching its calls and copying its records (as one process per device);
        ``shard``, each call's worlds split over the devices by XLA's partitioner
        (:func:`stride_jax.sim.rollout_mjx.collect`). The same records to float rounding.
      seed: PRNG seed of randomisation, exploration and the split.
      randomized: apply the hidden randomisation.
      stochastic: a contact residual that is stochastic given the state: ground patches of
        varying friction and softness along the path, several pushes per episode, rough ground
        (a heightfield drawn per episode; :func:`stride_jax.robots.stochastic`; implies
        ``randomized``).
      policy: a PPO run folder whose policy explores (walking under velocity commands,
        :class:`stride_jax.control.walk.PolicyExplorer`); empty: the robot's own explorer.
      action_noise: with ``policy``, the largest per-episode std of the noise on its actions.
      slope_deg: the largest slope (degrees): each episode tilts gravity under the floor by an
        angle uniform in [0, slope_deg] towards a uniform heading
        (:attr:`stride_jax.robots.Randomization.slope_deg`; implies ``randomized``); the records
        carry the gravity (``gravity``), the models trained on them are told it. 0: level.
        A ``policy`` senses each episode's gravity, as its IMU would (explorers with
        ``senses_gravity``, :func:`stride_jax.sim.rollout_mjx.sensing_act`); the robots' own
        explorers act on the state alone.
      payload_kg_max: > 0: each episode's hidden payload is drawn uniformly in [0, this] kg
        (:attr:`stride_jax.robots.Randomization.payload_kg`, replacing the robot's own range;
        implies ``randomized``, as ``payload_body`` does). 0: the robot's own range.
      payload_body: the body that carries the hidden payload, by name
        (:attr:`~stride_jax.robots.Randomization.payload_body`; "": the robot's own, its base
        body unless it names another); a name the robot lacks fails before any episode,
        listing its bodies.
      out: output folder; empty means ``data/<robot>``.
      distributed: several processes share the episodes (:mod:`stride_jax.distributed`).
    """

    robot: str = "pendulum"
    backend: str = "auto"
    episodes: int = 64
    seconds: float = 0.0
    batch: int = 0
    split: str = "threads"
    seed: int = 0
    randomized: bool = True
    stochastic: bool = False
    policy: str = ""
    action_noise: float = 0.3
    slope_deg: float = 0.0
    payload_kg_max: float = 0.0
    payload_body: str = ""
    out: str = ""
    distributed: DistributedConfig = DistributedConfig()


PRESETS = {
    "tiny": DataConfig(episodes=8, seconds=1.0),
    "default": DataConfig(),
    "paper": DataConfig(episodes=4096, backend="mjx", batch=1024),
}


def resolve_backend(backend: str) -> str:
    if backend == "auto":
        return "cpu" if jax.default_backend() == "cpu" else "mjx"
    if backend != "cpu" and backend not in rollout_mjx.BACKENDS:
        raise ValueError(f"unknown backend {backend!r}; use cpu, "
                         f"{', '.join(rollout_mjx.BACKENDS)} or auto")
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
    if not 0 <= cfg.slope_deg < 90:
        raise ValueError(f"slope_deg={cfg.slope_deg!r}: need a slope in [0, 90) degrees")
    if cfg.slope_deg and not robot.floating_base:
        raise ValueError(f"slope_deg={cfg.slope_deg!r}: {cfg.robot} has a fixed base (a slope "
                         "is the tilt of a walking robot's ground; a fixed base's gravity is "
                         "its model's)")
    if cfg.slope_deg:
        robot = dataclasses.replace(robot, randomization=dataclasses.replace(
            robot.randomization, slope_deg=(0.0, float(cfg.slope_deg))))
    if not (math.isfinite(cfg.payload_kg_max) and cfg.payload_kg_max >= 0):
        raise ValueError(f"payload_kg_max={cfg.payload_kg_max!r}: need a load >= 0 kg (0: the "
                         "robot's own range)")
    if cfg.payload_kg_max or cfg.payload_body:
        r = robot.randomization
        robot = dataclasses.replace(robot, randomization=dataclasses.replace(
            r, payload_kg=(0.0, float(cfg.payload_kg_max)) if cfg.payload_kg_max else r.payload_kg,
            payload_body=cfg.payload_body or r.payload_body))
    if explorer is not None:
        robot = dataclasses.replace(robot, explorer=explorer)
    if robot is not sm.robot:
        sm = dataclasses.replace(sm, robot=robot)
    randomized = (cfg.randomized or cfg.stochastic or cfg.slope_deg > 0
                  or cfg.payload_kg_max > 0 or bool(cfg.payload_body))
    if randomized:
        randomize.payload_body_id(sm)  # a body the robot lacks: an error before any episode
    if cfg.episodes < 3:
        raise ValueError(f"episodes must be >= 3 (train/val/test split), got {cfg.episodes}")
    if not math.isfinite(cfg.seconds) or cfg.seconds < 0:
        raise ValueError(f"seconds={cfg.seconds!r}: need an episode length >= 0 "
                         f"(0: the robot's own, {sm.robot.episode_s:g} s)")
    seconds = cfg.seconds or sm.robot.episode_s
    n_steps = int(round(seconds / sm.robot.ctrl_dt))
    if n_steps < 2:
        raise ValueError(f"seconds={seconds:g} is {n_steps} control step(s) of "
                         f"{sm.robot.ctrl_dt:g} s: an episode needs at least 2")
    rollout_mjx.check_split(cfg.split)
    backend = resolve_backend(cfg.backend)
    key = jax.random.key(cfg.seed)
    part = distributed.share(cfg.episodes)  # all of them for a single process
    quiet = not distributed.is_main()
    t0 = time.perf_counter()
    if backend in rollout_mjx.BACKENDS:
        with tqdm(total=part.stop - part.start, desc=f"{cfg.robot} {backend}", unit="episode",
                  disable=quiet) as bar:
            ep = rollout_mjx.collect(sm, key, cfg.episodes, n_steps, cfg.batch or None,
                                     randomized, bar.update, part,
                                     impl=rollout_mjx.BACKENDS[backend], split=cfg.split)
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
        model.robot_meta(sm), backend=backend, seed=cfg.seed,
        exploration=type(sm.robot.explorer).__name__,
        explorer=repr(explorer) if explorer is not None else None,
        randomization=dataclasses.asdict(sm.robot.randomization) if randomized else None,
        config=dataclasses.asdict(cfg), generation_seconds=seconds_taken,
    )
    ds = dataset.save(out, ep, meta)
    distributed.barrier("dataset written")
    return ds


def run(cfg: DataConfig, command: str = "stride data", log=print) -> dataset.Dataset:
    """``stride data``: builds the policy's explorer when ``cfg.policy`` is set, generates the
    dataset, draws its summary plot and says what it wrote."""
    from stride_jax.sim import plots
    explorer = None
    if cfg.policy:
        from stride_jax.control import walk
        explorer = walk.PolicyExplorer(cfg.policy, cfg.action_noise,
                                       max_seconds=cfg.seconds or 60.0)
    ds = generate(cfg, explorer)
    png = plots.dataset_summary(ds)
    m = ds.meta
    log(f"wrote {ds.path}: {m['n_episodes']} episodes x {m['n_steps']} steps of {m['robot']} "
        f"({m['backend']}, {m['generation_seconds']:.1f} s), valid fraction "
        f"{m['valid_fraction']:.2f}; summary plot {png}")
    return ds
