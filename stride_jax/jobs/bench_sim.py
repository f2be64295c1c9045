"""``stride bench-sim`` / ``make bench-sim``: simulation steps per second.

Two MJX measurements per robot and batch size: ``physics`` is a jitted, vmapped ``lax.scan`` of
``mjx.step`` (the number MuJoCo Playground quotes), ``collect`` is the full data pipeline
(randomised worlds, explorer, recording). ``warp`` is the same two through MuJoCo Warp's kernels
(MJX's ``impl="warp"``), ``cpu`` the ``mujoco.rollout`` backend's collect.
Each is timed after a compile-and-warm-up call, as the median of ``repeats`` calls.
"""

from __future__ import annotations

import copy
import dataclasses
import os
import pathlib
import platform

import jax
import jax.numpy as jnp
from mujoco import mjx

from stride_jax.jobs import bench_table
from stride_jax.sim import mjx_warp, model, rollout_cpu, rollout_mjx
from stride_jax.timing import median_time


@dataclasses.dataclass(frozen=True)
class BenchConfig:
    """Attributes:
      robots: comma-separated robot names.
      backends: comma-separated, of mjx, warp and cpu.
      batches: comma-separated batch sizes (worlds).
      steps: control steps per call (each is the robot's n_substeps simulation steps).
      repeats: timed calls per measurement (median reported).
      iterations: override the robots' constraint-solver iterations (0 keeps them).
      ls_iterations: override their line-search iterations (0 keeps them).
      split: how several local devices share the ``collect`` rows' worlds, as ``stride data
        --split`` (:func:`stride_jax.sim.rollout_mjx.collect`).
      out: results folder (``bench_sim_<cpu|gpu>.json`` and ``.md``).
    """

    robots: str = "go1,g1"
    backends: str = "cpu"
    batches: str = "16,64"
    steps: int = 100
    repeats: int = 3
    iterations: int = 0
    ls_iterations: int = 0
    split: str = "threads"
    out: str = "results/throughput"


PRESETS = {
    "tiny": BenchConfig(robots="pendulum", batches="16", steps=5, repeats=1),
    "default": BenchConfig(),
    "gpu": BenchConfig(backends="mjx,warp", batches="1024,8192", steps=20, repeats=3),
}


def _physics_fn(sm: model.SimModel, batch: int, n_steps: int, impl: str = "jax"):
    if impl == "warp":
        mjx_warp.check_devices()
        mx, template = mjx_warp.put_model(sm.mj), mjx_warp.layout(sm, sm.mj, batch).template
    else:
        mx = mjx.put_model(sm.mj)
        template = mjx.make_data(mx)
    qpos = jnp.asarray(sm.info.qpos0)

    def one(key):
        d = template.replace(qpos=qpos.at[7:].add(0.01 * jax.random.normal(key, (sm.mj.nq - 7,)))
                                      if sm.robot.floating_base else qpos)
        with jax.default_matmul_precision(rollout_mjx.PRECISION):  # as the data's physics
            d = jax.lax.fori_loop(0, n_steps * sm.n_substeps, lambda _, dd: mjx.step(mx, dd), d)
        return d.qpos

    fn = jax.jit(jax.vmap(one))
    keys = jax.random.split(jax.random.key(0), batch)
    sharding = rollout_mjx.world_sharding(batch, rollout_mjx.mjx_devices())
    if sharding is not None:
        keys = jax.device_put(keys, sharding)
    return lambda: jax.block_until_ready(fn(keys))


def _with_solver(sm: model.SimModel, cfg: BenchConfig) -> model.SimModel:
    if not (cfg.iterations or cfg.ls_iterations):
        return sm
    mj = copy.copy(sm.mj)
    mj.opt.iterations = cfg.iterations or mj.opt.iterations
    mj.opt.ls_iterations = cfg.ls_iterations or mj.opt.ls_iterations
    return dataclasses.replace(sm, mj=mj)


def measure(cfg: BenchConfig, on_row=None) -> list[dict]:
    """Every (robot, backend, batch) row of ``cfg``; ``on_row(rows)`` after each."""
    unknown = set(cfg.backends.split(",")) - {"cpu", *rollout_mjx.BACKENDS}
    if unknown:
        raise ValueError(f"unknown backends {sorted(unknown)}; use "
                         f"{', '.join(rollout_mjx.BACKENDS)} and cpu")
    rollout_mjx.check_split(cfg.split)
    rows = []
    for name in cfg.robots.split(","):
        sm = _with_solver(model.load(name), cfg)
        for backend in cfg.backends.split(","):
            for batch in (int(b) for b in cfg.batches.split(",")):
                sim_steps = batch * cfg.steps * sm.n_substeps
                if backend in rollout_mjx.BACKENDS:
                    impl = rollout_mjx.BACKENDS[backend]
                    t_phys = median_time(_physics_fn(sm, batch, cfg.steps, impl), cfg.repeats)
                    t_coll = median_time(rollout_mjx.device_call(
                        sm, cfg.steps, batch, impl=impl, split=cfg.split), cfg.repeats)
                    modes = [("physics", t_phys), ("collect", t_coll)]
                else:
                    key = jax.random.key(1)
                    modes = [("collect", median_time(
                        lambda: rollout_cpu.collect(sm, key, batch, cfg.steps), cfg.repeats))]
                for mode, t in modes:
                    row = dict(robot=name, backend=backend, mode=mode, batch=batch,
                               iterations=sm.mj.opt.iterations,
                               ls_iterations=sm.mj.opt.ls_iterations,
                               sim_steps=sim_steps, seconds=t, steps_per_s=sim_steps / t)
                    rows.append(row)
                    if on_row:
                        on_row(rows)
                    print(f"{name:18s} {backend:4s} {mode:8s} batch {batch:6d}: "
                          f"{row['steps_per_s']:12,.0f} steps/s", flush=True)
    return rows


def write(rows: list[dict], cfg: BenchConfig, command: str) -> pathlib.Path:
    """``<out>/bench_sim_<cpu|gpu>.{json,md}`` (:mod:`stride_jax.jobs.bench_table`)."""
    devices = [f"{d.platform}:{d.device_kind}" for d in jax.local_devices()]
    env = dict(command=command, devices=devices, cpu_count=os.cpu_count(),
               machine=platform.machine(), jax=jax.__version__, config=dataclasses.asdict(cfg))
    about = f"Devices: {', '.join(devices)}; {os.cpu_count()} CPU cores; jax {jax.__version__}"
    return bench_table.write(
        cfg.out, "bench_sim", "Simulation throughput", command, env, about,
        ["robot", "backend", "mode", "solver iters (ls)", "worlds:", "sim steps/s:"], rows,
        lambda r: [r["robot"], r["backend"], r["mode"],
                   f"{r['iterations']} ({r['ls_iterations']})", str(r["batch"]),
                   f"{r['steps_per_s']:,.0f}"])


def run(cfg: BenchConfig, command: str = "stride bench-sim") -> pathlib.Path:
    """``stride bench-sim``: measures every row, rewriting the table after each."""
    rows = measure(cfg, on_row=lambda rows: write(rows, cfg, command))
    path = write(rows, cfg, command)
    print(f"wrote {path}")
    return path
