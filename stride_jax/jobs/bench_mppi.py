"""``stride bench-mppi`` / ``make bench-mppi``: one jitted MPPI planning step per robot, model,
K and H.

Each measurement builds a model of the given size for the robot (parameters at initialisation:
latency does not depend on training), an MPPI planner with a velocity-tracking cost, jits its
step once, and reports the median wall time of ``repeats`` steps (after a warm-up call) with
``block_until_ready``. The FLOP floor is ``K x H`` times the FLOPs of one model control step
(:func:`control_step_flops`: XLA's count of a step compiled without loops -- XLA counts a loop
body once, not once per trip -- with the substeps and residual evaluations added) divided by the
machine's measured peak (a large float32 matmul); the ratio says how far from compute-bound the
step runs. The planner's own work (noise, costs, weights) is left out: the floor is a lower bound.

The model ``oracle`` plans through the simulator itself (the robot's MJX model, its simulation
substeps per control step: the MJX-MPPI of tools like hydrax), at the same K and H, so each
learned model's speed against planning through physics is measured in one run (the table's
"x oracle" column: the oracle's time over the model's). It has no FLOP floor.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import os
import pathlib
import platform
import time
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from mujoco import mjx

from stride_jax.control import envs, mppi
from stride_jax.dynamics import fused, models, stride
from stride_jax.jobs import bench_table
from stride_jax.sim import model as sim_model
from stride_jax.sim import rollout_mjx
from stride_jax.timing import median_time, peak_flops
from stride_jax.train.setup import model_config


@dataclasses.dataclass(frozen=True)
class BenchConfig:
    """Attributes:
      robots: comma-separated robot names.
      models: comma-separated model names (``models.MODELS``), and ``oracle``: planning through
        the robot's MJX model.
      samples: comma-separated K values.
      horizons: comma-separated H values.
      hidden, depth: network size (the paper's: 256 x 3).
      nfe: residual evaluations for generative models (0: each model's default).
      shared_lnn: structured models with one network for L and V (``LNNConfig.shared``).
      kernel: how the models' networks run: ``xla``, ``xla-bf16`` (XLA with the networks'
        products in bfloat16: CPUs with bfloat16 dot instructions), or fused kernels (``pallas``,
        ``pallas-bf16``; ``stride_jax.dynamics.fused``, GPUs; ``pallas-step[-bf16]``: STRIDE's
        whole model step as one kernel where it applies, ``stride_jax.dynamics.fused_step``).
      substeps: model evaluations per control step in the planner's rollouts (0: the robot's
        simulation substeps; 1 integrates at the control period, with the implicit servo).
      unroll: horizon steps per loop iteration of the planner's rollouts (0: the whole horizon;
        see ``MPPIConfig.unroll``).
      repeats: timed planning steps per measurement (median reported).
      out: results folder (``bench_mppi_<cpu|gpu>.json`` and ``.md``).
    """

    robots: str = "go1,g1"
    models: str = "stride,delan,onn,oracle"
    samples: str = "64,256,1024"
    horizons: str = "10,20,30"
    hidden: int = 256
    depth: int = 3
    nfe: int = 0
    shared_lnn: bool = False
    kernel: str = "xla"
    substeps: int = 0
    unroll: int = 1
    repeats: int = 5
    out: str = "results/mppi_latency"


PRESETS = {
    "tiny": BenchConfig(robots="go1", models="delan,oracle", samples="8", horizons="4",
                        hidden=32, depth=1, repeats=1),
    "target": BenchConfig(robots="go1", models="stride,delan,onn", samples="128", horizons="16"),
    "target-coarse": BenchConfig(robots="go1", models="stride,delan", samples="128",
                                 horizons="16", substeps=1),
    # The 50 Hz CPU target with planning-sized networks (the paper's 256 x 3 is below its FLOP
    # floor on 2 cores; `experiments/probes/planning_sizes.sh` measures what the smaller sizes cost in
    # accuracy): run with --hidden 64 or 128.
    "target-small": BenchConfig(robots="go1", models="stride,delan", samples="128",
                                horizons="16", hidden=64, substeps=1),
    "default": BenchConfig(),
    # One device call's worth (the full default grid compiles ~54 planners): both robots, the
    # issue's largest K and H and a small one, at the control rate.
    "gpu": BenchConfig(samples="256,1024", horizons="10,30", substeps=1),
}


def tracking_cost(spec, target_speed: float = 1.0):
    """Base forward-velocity tracking, upright posture, small actions (cheap next to the model)."""
    def cost(q, qd, u, t):
        if not spec.floating_base:
            return jnp.sum(qd ** 2) + 1e-3 * jnp.sum(u ** 2)
        return ((qd[0] - target_speed) ** 2 + qd[1] ** 2 + 0.1 * jnp.sum(qd[3:6] ** 2)
                + jnp.sum(q[4:6] ** 2) + 1e-3 * jnp.sum(u ** 2))
    return cost


@functools.lru_cache(maxsize=None)
def _robot(name: str):
    sm = sim_model.load(name)
    meta = sim_model.robot_meta(sm)
    return sm, meta, models.spec_from_meta(meta), models.Actuation.from_meta(meta)


def _flops(compiled) -> float:
    cost = compiled.cost_analysis()
    cost = cost[0] if isinstance(cost, (list, tuple)) else cost
    return float(cost.get("flops", float("nan"))) if cost else float("nan")


def control_step_flops(model_name: str, spec, act: models.Actuation,
                       model_cfg: stride.StructuredConfig, params) -> float:
    """FLOPs of one control step of a model (one rollout step of the planner), counted without
    loops: XLA counts a loop body once, so the step is compiled with one substep and one residual
    evaluation, and the rest is added: ``substeps x (eval(nfe=1) + (nfe - 1) x 2 P_res)``, with
    ``2 P_res`` the multiply-adds of one pass of the residual network (``P_res`` weights)."""
    one = dataclasses.replace(act, n_substeps=1)
    model_cfg = dataclasses.replace(model_cfg, kernel="xla")  # XLA counts its own ops only
    model = models.make(model_name, spec, one, model_cfg, stride.Scales())
    nu = len(act.dof)
    q = jnp.zeros(spec.nq).at[3].set(1.0) if spec.floating_base else jnp.zeros(spec.nq)
    step = jax.jit(lambda p: model.step(p, q, jnp.zeros(spec.nv), jnp.zeros(nu),
                                        jax.random.key(0), nfe=1 if model.stochastic else None))
    per_eval = _flops(step.lower(params).compile())
    structured = models.MODELS[model_name][0] == "structured"
    extra = 0.0
    if model.stochastic:
        p_res = sum(x.size for x in jax.tree.leaves(params["residual"] if structured else params))
        extra = (model_cfg.nfe - 1) * 2.0 * p_res
    # next-observation models take one evaluation per control step, whatever the substeps
    return (act.n_substeps if structured else 1) * (per_eval + extra)


class Setup(NamedTuple):
    """One benchmarked planner: ``step(state, q0, qd0)`` to jit, its inputs, and what the FLOP
    count needs."""

    step: Callable
    state: mppi.MPPIState
    q0: jax.Array
    qd0: jax.Array
    model: models.Model | None  # None for the oracle
    params: dict | None
    spec: Any
    act: models.Actuation
    model_cfg: stride.StructuredConfig
    devices: int  # the devices its samples are split over


def setup(robot: str, model_name: str, K: int, H: int, cfg: BenchConfig) -> Setup:
    """The planner :func:`measure` times (also read by ``experiments/probes/mppi_hlo_ops.py``): a model
    of ``cfg``'s size at initialisation, MPPI with ``K`` samples and horizon ``H`` and the
    tracking cost, from the robot's home pose."""
    sm, meta, spec, act = _robot(robot)
    lo, hi = np.asarray(meta["ctrl_range"], np.float32).T
    if model_name == "oracle":
        dynamics, model, params, model_cfg = envs.mjx_step_fn(sm.n_substeps,
                                                              mjx.put_model(sm.mj)), None, None, None
    elif cfg.substeps:
        act = dataclasses.replace(act, dt=act.dt * act.n_substeps / cfg.substeps,
                                  n_substeps=cfg.substeps)
    if model_name != "oracle":
        model_cfg = dataclasses.replace(model_config(model_name, meta, cfg.hidden, cfg.depth,
                                                     cfg.nfe, cfg.shared_lnn),
                                        kernel=cfg.kernel)
        model = models.make(model_name, spec, act, model_cfg, stride.Scales())
        params = model.init(jax.random.key(0))
        dynamics = functools.partial(model.step, params)
    # the oracle's MJX solver on a CPU's host devices: see rollout_mjx.mjx_devices
    devices = rollout_mjx.mjx_devices() if model_name == "oracle" else None
    planner = mppi.make(mppi.MPPIConfig(samples=K, horizon=H, unroll=cfg.unroll or True),
                        dynamics, tracking_cost(spec), lo, hi,
                        sharding=mppi.sample_sharding(devices))
    q0 = jnp.asarray(sm.info.qpos0)
    state = planner.init(jax.random.key(1), jnp.broadcast_to(q0[
        np.asarray(act.dof) + (1 if spec.floating_base else 0)], (H, len(lo))))
    return Setup(planner.step, state, q0, jnp.zeros(spec.nv), model, params, spec, act,
                 model_cfg, len(devices or jax.local_devices()))


def measure(robot: str, model_name: str, K: int, H: int, cfg: BenchConfig,
            peak: float) -> dict:
    b = setup(robot, model_name, K, H, cfg)
    args = (b.state, b.q0, b.qd0)
    t0 = time.perf_counter()
    compiled = jax.jit(b.step).lower(*args).compile()
    compile_s = time.perf_counter() - t0
    xla_flops = _flops(compiled)
    ms = 1e3 * median_time(lambda: jax.block_until_ready(compiled(*args)), cfg.repeats)
    oracle = b.model is None
    flops = float("nan") if oracle else K * H * control_step_flops(
        model_name, b.spec, b.act, b.model_cfg, b.params)
    floor_ms = 1e3 * flops / peak
    return dict(robot=robot, model=model_name, K=K, H=H,
                substeps=_robot(robot)[0].n_substeps if oracle else b.act.n_substeps,
                unroll=cfg.unroll, kernel="mjx" if oracle else cfg.kernel,
                nfe=b.model_cfg.nfe if not oracle and b.model.stochastic else None, ms=ms,
                hz=1e3 / ms,
                gflop=flops / 1e9, xla_gflop=xla_flops / 1e9, floor_ms=floor_ms,
                ratio=ms / floor_ms if floor_ms > 0 else float("nan"), compile_s=compile_s,
                devices=b.devices)


def _oracle_devices_note(rows: list[dict], n_devices: int) -> str:
    """Says where the oracle planned on fewer devices than the learned models: MJX on a CPU's
    host devices keeps to one of them unless XLA's pool is large enough
    (:func:`stride_jax.sim.rollout_mjx.mjx_devices`)."""
    fewer = {r.get("devices", n_devices) for r in rows
             if r["model"] == "oracle" and r.get("devices", n_devices) < n_devices}
    if not fewer:
        return ""
    return (f" The oracle's samples ran on {min(fewer)} of the {n_devices} devices (MJX's solver "
            "on a CPU's host devices hangs XLA's default pool; `NPROC` = cores + devices lets "
            "it use all, at a cost to the learned models: `stride_jax/_env.py`).")


def _products(kernel: str) -> str:
    """The products' type whose matmul peak gives the floor: bfloat16 where the kernel choice
    runs the networks' products in it."""
    bf16 = fused.kernel_dtype(kernel) == jnp.bfloat16 or fused.products(kernel) == "bfloat16"
    return "bfloat16" if bf16 else "float32"


def run(cfg: BenchConfig, command: str = "stride bench-mppi") -> list[dict]:
    """``stride bench-mppi``: measures every (robot, model, K, H), rewriting the table after
    each; returns the rows."""
    peak = peak_flops(dtype=_products(cfg.kernel))
    rows = []
    split = lambda s: [x for x in s.split(",") if x]
    for robot, name, K, H in itertools.product(split(cfg.robots), split(cfg.models),
                                               map(int, split(cfg.samples)),
                                               map(int, split(cfg.horizons))):
        r = measure(robot, name, K, H, cfg, peak)
        rows.append(r)
        print(f"{robot} {name} K={K} H={H}: {r['ms']:.2f} ms ({r['hz']:.0f} Hz)"
              + ("" if name == "oracle" else
                 f", {r['gflop']:.2f} GFLOP, {r['ratio']:.0f}x the FLOP floor"), flush=True)
        path = write(rows, cfg, command, peak)
    if rows:
        print(f"wrote {path} ({len(rows)} rows)")
    return rows


def _kernel_note(kernel: str) -> str:
    if kernel == "xla":
        return ""
    if not fused.fused(kernel):
        return f", XLA's ops with the networks' products in bfloat16 ({kernel})"
    if fused.whole_step(kernel):
        return f", STRIDE's model step as one fused kernel where it applies ({kernel})"
    return f", network passes as fused kernels ({kernel})"


def write(rows: list[dict], cfg: BenchConfig, command: str, peak: float) -> pathlib.Path:
    """``<out>/bench_mppi_<cpu|gpu>.{json,md}`` (:mod:`stride_jax.jobs.bench_table`); the
    ``x oracle`` column is the oracle's time over the model's at the same robot, K and H."""
    device = jax.devices()[0]
    env = dict(command=command, backend=jax.default_backend(), device=device.device_kind,
               n_devices=jax.device_count(), cpu=platform.processor() or platform.machine(),
               peak_gflops=peak / 1e9, jax=jax.__version__, config=dataclasses.asdict(cfg),
               xla_flags=os.environ.get("XLA_FLAGS", ""))
    about = (f"Device: {env['device']} ({env['backend']}), measured {_products(cfg.kernel)} matmul peak "
             f"{env['peak_gflops']:.0f} GFLOP/s; "
             + (f"{env['n_devices']} devices, the samples split over them; "
                if env["n_devices"] > 1 else "")
             + f"jax {env['jax']}; XLA_FLAGS `{env['xla_flags'] or '-'}`; rollouts unrolled "
             f"{'fully' if not cfg.unroll else f'{cfg.unroll} step(s) per loop iteration'}. "
             f"Networks {cfg.hidden} x {cfg.depth}"
             f"{' (L and V from one network)' if cfg.shared_lnn else ''} at initialisation"
             + _kernel_note(cfg.kernel)
             + "; one jitted planning step (K rollouts of H control steps, each the robot's "
             "simulation substeps) with block_until_ready; median of "
             f"{cfg.repeats}. FLOP floor = K x H x the FLOPs of one model control step "
             "(`control_step_flops`: counted without loops) / peak; the planner's own work "
             "(noise, costs, weights) is left out, so the floor is a lower bound."
             + _oracle_devices_note(rows, env["n_devices"]))
    oracle_ms = {(r["robot"], r["K"], r["H"]): r["ms"] for r in rows if r["model"] == "oracle"}
    num = lambda x, f: "-" if not np.isfinite(x) else format(x, f)  # noqa: E731

    def cells(r: dict) -> list[str]:
        vs = oracle_ms.get((r["robot"], r["K"], r["H"]))
        speedup = "-" if vs is None or r["model"] == "oracle" else f"{vs / r['ms']:.1f}"
        return [r["robot"], r["model"], str(r["nfe"] or "-"), str(r.get("substeps", "-")),
                str(r.get("unroll", 1) or "all"), str(r["K"]), str(r["H"]), f"{r['ms']:.2f}",
                f"{r['hz']:.0f}", num(r["gflop"], ".2f"), num(r["floor_ms"], ".3f"),
                num(r["ratio"], ".0f"), speedup]

    return bench_table.write(
        cfg.out, "bench_mppi", "MPPI step latency", command, env, about,
        ["robot", "model", "NFE", "substeps", "unroll", "K:", "H:", "median ms:", "Hz:",
         "GFLOP:", "FLOP floor ms:", "ratio:", "x oracle:"], rows, cells)
