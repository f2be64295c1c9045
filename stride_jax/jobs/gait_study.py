"""The gait study: the named gaits as parameter settings of the Go1 gait reference, and what
MPPI picks when the gait parameters are free (in closed loop: :mod:`stride_jax.jobs.closed_loop`)."""

from __future__ import annotations

import dataclasses
import json
import pathlib
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np
from mujoco import mjx

from stride_jax.control import envs, gait as gait_lib
from stride_jax.control.episode import metrics, mjx_step_fn, run_episode
from stride_jax.control.mppi import MPPIConfig
from stride_jax.control.planning import (PlanningConfig, make_planner, make_planning,
                                         mppi_config)
from stride_jax.control.scenarios import schedule, Scenario
from stride_jax.io import atomic_write_text, code_version
from stride_jax.sim import model as sim_model


@dataclasses.dataclass(frozen=True)
class GaitStudyConfig:
    """Attributes:
      speeds: comma-separated forward commands (m/s).
      starts: random initial gaits per speed for the planner.
      seconds: episode length (s).
      freq: frequency of the open-loop named gaits (Hz).
      mppi: the planner (oracle dynamics): samples, horizon, ... (``--mppi.samples``).
      planning: its task side, in gait mode (``--planning.noise-std``, ``--planning.gait-noise``).
      out: results folder (``closed_loop_gait.json``/``.md``).
      seed: initial gaits and planner keys.
    """

    speeds: str = "0.5,1.0,2.0"
    starts: int = 2
    seconds: float = 4.0
    freq: float = 2.0
    mppi: MPPIConfig = MPPIConfig(horizon=25)
    planning: PlanningConfig = PlanningConfig(gait=True, noise_std=0.05)
    out: str = "results/closed_loop/closed_loop_gait"
    seed: int = 0

    # the flat flags of before still answer
    FLAG_ALIASES: ClassVar[dict[str, str]] = {
        "mppi.samples": "--samples", "mppi.horizon": "--horizon",
        "planning.noise_std": "--noise-std", "planning.gait_noise": "--gait-noise"}

    def __post_init__(self):
        if not self.planning.gait:
            raise ValueError("the gait study plans gait parameters: planning.gait must be on")


def _planner(samples: int, horizon: int) -> MPPIConfig:
    return MPPIConfig(samples=samples, horizon=horizon)


GAIT_PRESETS = {
    "tiny": GaitStudyConfig(speeds="1.0", starts=1, seconds=0.3, mppi=_planner(8, 4),
                            out="results/closed_loop/closed_loop_gait_tiny"),
    "cpu": GaitStudyConfig(speeds="0.5,1.5", starts=1, seconds=2.0, mppi=_planner(32, 15),
                           out="results/closed_loop/closed_loop_gait_cpu"),
    "default": GaitStudyConfig(mppi=_planner(256, 25)),
    "gpu": GaitStudyConfig(mppi=_planner(1024, 30), starts=3,
                           out="results/closed_loop/closed_loop_gait_gpu"),
}


def gait_study(cfg: GaitStudyConfig, command: str = "", log=print) -> dict:
    """(a) Each named gait's reference alone (no planner) in MJX: which gait the feet show, and
    whether it stays up. (b) MPPI with the oracle choosing gait parameters from random initial
    gaits at each speed: the gait it settles on (median of the second half) and the feet's."""
    code = code_version()  # the code this process runs: read now, not when the result is written
    sm = sim_model.load("go1")
    mx = mjx.put_model(sm.mj)
    slots = envs.contact_slots(mx)
    n_steps = max(1, int(round(cfg.seconds / sm.robot.ctrl_dt)))
    planning = make_planning(cfg.planning, envs.config("go1"), sm, mjx_step_fn(sm, mx))
    planner = make_planner(planning, mppi_config(cfg.mppi, cfg.planning, planning))
    nu = sm.info.nu

    def open_loop(gait_u, starts, values):
        pl = planning._replace(policy=lambda q, qd: gait_u)
        return run_episode(sm, mx, slots, pl, None, n_steps, starts, values, jax.random.key(0))

    def planned(init_u, starts, values, key):
        pl = planning._replace(nominal_u=init_u)
        return run_episode(sm, mx, slots, pl, planner, n_steps, starts, values, key)

    open_loop, planned = jax.jit(open_loop), jax.jit(planned)
    rows = []
    rng = np.random.default_rng(cfg.seed)
    for speed in [float(v) for v in cfg.speeds.split(",") if v]:
        starts, values = schedule(Scenario("walk", ((0.0, speed, 0.0, 0.0),)))
        for name in gait_lib.NAMED:
            g = gait_lib.named(name, freq=cfg.freq)
            u = gait_lib.join_action(jnp.zeros(nu), g)
            m = metrics(open_loop(u, starts, values), 0.5)
            rows.append(dict(speed=speed, mode="open loop", start=name, **m))
            log(f"{speed} m/s open-loop {name}: feet show {m.get('contact_gait')}, fell "
                f"{m['fell']}, mean vx {m['mean_vx']:.2f}")
        for i in range(cfg.starts):
            g0 = gait_lib.Gait(jnp.float32(cfg.freq), jnp.float32(0.5),
                               jnp.asarray(rng.uniform(0, 1, 4), jnp.float32))
            u0 = gait_lib.join_action(jnp.zeros(nu), g0)
            trace = planned(u0, starts, values, jax.random.key(cfg.seed + i))
            half = jax.tree.map(lambda x: x[n_steps // 2:], trace)
            m = metrics(half, 0.0)
            m["start_gait"], m["start_dist"] = gait_lib.classify(np.asarray(g0.offsets))
            rows.append(dict(speed=speed, mode="MPPI (oracle)", start=f"random {i}", **m))
            log(f"{speed} m/s MPPI from {m['start_gait']} ({m['start_dist']:.2f} away): plans "
                f"{m.get('plan_gait')} ({m.get('plan_gait_dist', float('nan')):.2f}), feet show "
                f"{m.get('contact_gait')}, fell {m['fell']}")
    out = pathlib.Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    result = dict(command=command, backend=jax.default_backend(), code=code,
                  device=jax.devices()[0].device_kind, config=dataclasses.asdict(cfg), rows=rows)
    atomic_write_text(out / "closed_loop_gait.json", json.dumps(result, indent=1))
    fmt = lambda x, f="{:.2f}": "-" if x is None or (isinstance(x, float) and np.isnan(x)) else (
        f.format(x))
    lines = ["# Gaits as parameter settings (Go1, MJX)", "", f"Command: `{command}`", "",
             f"Device: {result['device']} ({result['backend']}). Open loop: the gait reference "
             f"of each named gait at {cfg.freq} Hz, duty 0.5, no planner. MPPI: oracle dynamics, "
             f"K={cfg.mppi.samples}, H={cfg.mppi.horizon}, gait parameters (frequency, duty, "
             "four offsets) "
             "planned per rollout from a random initial gait; statistics of the second half. "
             "'feet show': the named pattern the measured contacts fit best (score: in-phase "
             "minus anti-phase contact correlation, 1 is a clean pattern).", "",
             "| speed (m/s) | mode | start | planned gait (dist) | Hz | duty | feet show (score) | "
             "fell | mean vx | vel RMSE |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        plan = (f"{r['plan_gait']} ({fmt(r['plan_gait_dist'])})" if "plan_gait" in r else "-")
        feet = (f"{r['contact_gait']} ({fmt(r['contact_gait_score'])})" if "contact_gait" in r
                else "-")
        lines.append(f"| {r['speed']} | {r['mode']} | {r['start']} | {plan} | "
                     f"{fmt(r.get('plan_freq'))} | {fmt(r.get('plan_duty'))} | {feet} | "
                     f"{'yes' if r['fell'] else 'no'} | {fmt(r['mean_vx'])} | "
                     f"{fmt(r['vel_rmse'])} |")
    atomic_write_text(out / "closed_loop_gait.md", "\n".join(lines) + "\n")
    return result
