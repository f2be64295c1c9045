"""Dreamer-MPC ablation (issue 19, item 2): the PPO policy alone, MPPI through a learned model as
today, and the Dreamer-MPC switches added one at a time, in closed loop in MJX.

Rows (``variants``, cumulative, each one switch more than the one before):

* ``policy``: the PPO policy alone;
* ``mppi``: today's planner: noise around the shifted plan (``planning.noise_std``), ``policy_samples``
  policy candidates, horizon ``mppi.horizon``, the learned reward and the value fitted on the
  policy's rollouts, undiscounted;
* ``prior``: + policy-prior sampling, ``prior_fraction`` of the noise candidates around the
  policy's own closed-loop rollout through the model at the policy's action spread
  (``planning.prior_noise_std``);
* ``short``: + a short horizon (``short_horizon``) with the terminal value, discounted
  (``discount``, the value's gamma);
* ``value``: + the value refitted on the planner's own rollouts
  (:mod:`stride_jax.control.planner_value`, :func:`train_value`: collected by the ``short``
  planner through the same model on the nominal ground under random commands, never on the
  scenarios);
* ``error``: + the model's error where the planner goes: ``error_draws`` residual draws per step
  (their spread) and the learned one-step error model (``error_model``), rollouts cut at
  ``error_bound`` (0: calibrated, ``error_bound_scale`` x the model's mean one-step error in the
  closed loop x sqrt(horizon)) and down-weighted by ``error_weight``: every switch on.

One row outside the cumulative chain:

* ``prior_value``: ``prior`` (the full horizon) with the value refitted on the planner's own
  rollouts as its terminal value, discounted (``discount``): the value without the short horizon.

The value's data are collected by the ``value_collector`` variant's planner (``short`` by
default, as the first ablation ran; ``prior``, the full-horizon planner that stays up, is the
session-27 choice) into ``out/value`` (``out/value_<collector>`` for another collector).

Each variant is a :func:`stride_jax.jobs.closed_loop.run` into ``out/<variant>`` (resumable:
finished pairs are skipped, a trained value is reused); ``out/ablation.{json,md}`` gather the
rows (``scenario``, ``model``, ``variant``, ``vel_rmse``, ``fell``, ``ms_per_step``, ...).

    python experiments/dreamer_mpc.py --preset tiny          # CPU, about 5 minutes on 2 cores
    python experiments/dreamer_mpc.py --preset gpu           # one H100
"""

from __future__ import annotations

import dataclasses
import json
import math
import pathlib
import time
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np
from mujoco import mjx

import stride_jax
from stride_jax import config
from stride_jax.control import episode as episode_lib, learned, planner_value, ppo
from stride_jax.control import planning as planning_lib
from stride_jax.control.mppi import MPPIConfig
from stride_jax.control.planning import PlanningConfig
from stride_jax.io import atomic_write_text, code_version
from stride_jax.jobs import closed_loop
from stride_jax.jobs.closed_loop import ClosedLoopConfig
from stride_jax.sim import model as sim_model

VARIANTS = ("policy", "mppi", "prior", "short", "value", "error", "prior_value")  # the last apart
COLLECTORS = ("mppi", "prior", "short")


@dataclasses.dataclass(frozen=True)
class AblationConfig:
    """The ablation's rows and the Dreamer-MPC settings.

    Attributes:
      robot: ``go1`` or ``g1``.
      model: the learned dynamics model the planner variants use, ``NAME=RUN``.
      policy: PPO run folder (the ``policy`` row, candidates and the prior).
      learned: the learned reward and value fitted on the policy's rollouts.
      scenarios: comma-separated closed-loop scenarios.
      seconds: each scenario's duration (s).
      variants: comma-separated rows of :data:`VARIANTS`, cumulative.
      mppi: today's planner settings (``--mppi.samples``, ``--mppi.horizon`` ...).
      planning: the task side of the planner, as in the closed loop
        (:class:`~stride_jax.control.planning.PlanningConfig`): ``--planning.noise-std``, the
        plan-centred exploration std (rad), ``--planning.prior-noise-std``, the prior
        candidates' noise std (rad, the policy's own action spread), ...; the older
        ``--noise-std`` and ``--prior-noise-std`` still answer.
      prior_fraction: share of the noise candidates drawn around the policy (``prior`` on).
      short_horizon: the horizon from ``short`` on (control steps).
      discount: gamma of the running costs and terminal value from ``short`` on (the value's).
      error_draws: residual draws per rollout step whose spread is the predicted error.
      error_model: add the learned one-step error model (fitted with the planner's value).
      error_bound: cut rollouts whose accumulated predicted error exceeds this (m/s); 0:
        calibrated as ``error_bound_scale`` x the model's mean one-step error in the
        collection's closed loop x sqrt(short_horizon).
      error_bound_scale: see ``error_bound``.
      error_weight: cost per m/s of predicted error per kept step.
      value: collecting the planner's data and refitting the value (``--value.worlds`` ...).
      value_collector: the variant whose planner collects the value's data (``mppi``,
        ``prior`` or ``short``).
      kernel: how structured models run their networks (``xla``, ``pallas-step`` ...).
      settle_s: tracking errors count from this long after each command change (s).
      out: results folder.
      seed: planner key and terrain seed.
    """

    robot: str = "go1"
    model: str = "stride=results/models/go1/stride-s0"
    policy: str = "results/policies/ppo_go1"
    learned: str = "results/learned_go1/reward_value.msgpack"
    scenarios: str = "slope,rough,soft,changes"
    seconds: float = 6.0
    variants: str = ",".join(VARIANTS)
    mppi: MPPIConfig = MPPIConfig(samples=1024, horizon=20, policy_samples=64)
    planning: PlanningConfig = PlanningConfig()
    prior_fraction: float = 0.5
    short_horizon: int = 5
    discount: float = 0.97
    error_draws: int = 4
    error_model: bool = True
    error_bound: float = 0.0
    error_bound_scale: float = 2.0
    error_weight: float = 0.0
    value: planner_value.PlannerValueConfig = planner_value.PlannerValueConfig()
    value_collector: str = "short"
    kernel: str = "xla"
    settle_s: float = 0.5
    out: str = "results/dreamer_mpc_go1"
    seed: int = 0

    # The flat flags of earlier commands (recorded in results/) still answer.
    FLAG_ALIASES: ClassVar[dict[str, str]] = {"planning.noise_std": "--noise-std",
                                              "planning.prior_noise_std": "--prior-noise-std"}

    def __post_init__(self):
        unknown = [v for v in self.variants.split(",") if v and v not in VARIANTS]
        if unknown:
            raise ValueError(f"unknown variants {unknown}; known: {', '.join(VARIANTS)}")
        name, _, run = self.model.partition("=")
        if not (name and run):
            raise ValueError(f"model must be NAME=RUN (a trained dynamics model), got "
                             f"{self.model!r}")
        if not (self.policy and self.learned):
            raise ValueError("the ablation needs a policy and a learned reward/value")
        if self.value_collector not in COLLECTORS:
            raise ValueError(f"value_collector={self.value_collector!r} must be one of "
                             f"{', '.join(COLLECTORS)} (a planner that collects without the "
                             f"value it trains)")
        if self.short_horizon < 1:
            raise ValueError(f"short_horizon={self.short_horizon} must be >= 1")


PRESETS = {
    "tiny": AblationConfig(scenarios="changes", seconds=0.1, variants=",".join(VARIANTS),
                           mppi=MPPIConfig(samples=8, horizon=4, policy_samples=2),
                           short_horizon=2, error_draws=2, settle_s=0.0,
                           value=planner_value.PRESETS["tiny"], out="results/dreamer_mpc_tiny"),
    "default": AblationConfig(),
    "gpu": AblationConfig(),  # the defaults are the GPU run's (``results/dreamer_mpc_go1``)
}


def variant_config(cfg: AblationConfig, variant: str, learned: str | None = None,
                   error_model: str = "", error_bound: float = 0.0) -> ClosedLoopConfig:
    """The closed-loop configuration of one row (``learned``/``error_model``: the files the
    ``value`` and ``error`` rows use, ``error_bound``: the bound in m/s)."""
    if variant == "prior_value":
        base = variant_config(cfg, "prior")
        return dataclasses.replace(
            base, mppi=dataclasses.replace(base.mppi, discount=cfg.discount),
            learned=learned or cfg.learned, out=str(pathlib.Path(cfg.out) / variant))
    level = VARIANTS.index(variant)
    name, _, run = cfg.model.partition("=")
    m = cfg.mppi
    if level >= VARIANTS.index("prior"):
        m = dataclasses.replace(m, prior_fraction=cfg.prior_fraction)
    if level >= VARIANTS.index("short"):
        m = dataclasses.replace(m, horizon=cfg.short_horizon, discount=cfg.discount)
    if level >= VARIANTS.index("error"):
        m = dataclasses.replace(m, error_draws=cfg.error_draws, error_bound=error_bound,
                                error_weight=cfg.error_weight)
    return ClosedLoopConfig(
        robot=cfg.robot, models="policy" if variant == "policy" else cfg.model,
        scenarios=cfg.scenarios, seconds=cfg.seconds, mppi=m, planning=cfg.planning,
        policy=cfg.policy,
        learned=learned if learned and level >= VARIANTS.index("value") else cfg.learned,
        error_model=error_model if level >= VARIANTS.index("error") else "",
        kernel=cfg.kernel, settle_s=cfg.settle_s,
        out=str(pathlib.Path(cfg.out) / variant), seed=cfg.seed)


def train_value(cl_cfg: ClosedLoopConfig, cfg: planner_value.PlannerValueConfig, name: str,
                run: str, out: str | pathlib.Path, command: str = "", log=print,
                code: str | None = None) -> dict:
    """Collects the planner's data with ``cl_cfg``'s planner through the dynamics model ``run``
    (on the nominal ground), refits the value of ``cl_cfg.learned`` and fits the one-step
    error model; writes ``reward_value.msgpack``, ``error_model.msgpack`` and ``report.json``
    to ``out`` (:mod:`stride_jax.control.planner_value`). ``cl_cfg`` needs a policy and a
    learned reward and value. A file with ensembles (``stride fit-reward-value --members``,
    or an earlier refit's ``--ensemble``) is planned with as the closed loop plans with it
    (the rewards' mean, the values pessimistic) and its reward ensemble is written through
    whole; the value is refitted from its first member (the refit draws its own members).
    ``code``: the commit the job started from (default: the checkout's now)."""
    code = code or code_version()  # read before the work, not when the report is written
    if not (cl_cfg.policy and cl_cfg.learned):
        raise ValueError("the planner's value needs a policy and a learned reward/value "
                         "(--policy, --learned) to start from")
    t0 = time.monotonic()
    sm = sim_model.load(cl_cfg.robot)
    ppo_policy, _, env_cfg = ppo.load_policy(cl_cfg.policy)
    reward_params, value_params = learned.load(cl_cfg.learned, ensemble=True)
    value_start = value_params[0] if isinstance(value_params, list) else value_params
    mx = mjx.put_model(sm.mj)
    true_step = episode_lib.mjx_step_fn(sm, mx)
    step_fn = (episode_lib.learned_step_fn(run, sm, cl_cfg.kernel, cl_cfg.model_precision)
               if run else true_step)
    planning = planning_lib.make_planning(cl_cfg.planning, env_cfg, sm, step_fn, ppo_policy,
                                          (reward_params, value_params))
    planner = planning_lib.make_planner(
        planning, planning_lib.mppi_config(cl_cfg.mppi, cl_cfg.planning, planning))
    log(f"collecting the planner's data: {cfg.worlds} worlds x {cfg.seconds:g} s through {name}"
        " (one compiled run: no progress until it ends)")
    data = jax.jit(lambda k: planner_value.collect(planning, planner, sm, mx, true_step, env_cfg,
                                                   cfg, k))(jax.random.key(cfg.seed))
    data = jax.block_until_ready(data)
    t_collect = time.monotonic() - t0
    up = np.asarray(data.up)
    log(f"planner data: {cfg.worlds} worlds x {up.shape[1]} steps through {name} "
        f"({t_collect:.0f} s), up {up.mean():.0%} of steps, mean planner reward "
        f"{float(jnp.mean(data.closed.reward)):.4f}")
    new_value, err_params, report = planner_value.fit(jax.random.key(cfg.seed + 1), cfg,
                                                      value_start, data)
    report.update(command=command, code=code, model=name, run=run,
                  reward_members=len(reward_params) if isinstance(reward_params, list) else 1,
                  value_members_planned=(len(value_params) if isinstance(value_params, list)
                                         else 1),
                  seconds_collect=t_collect, seconds=time.monotonic() - t0,
                  config=dataclasses.asdict(cfg), planner=dataclasses.asdict(cl_cfg.mppi))
    out = pathlib.Path(out)
    out.mkdir(parents=True, exist_ok=True)
    learned.save(out / "reward_value.msgpack", reward_params, new_value)
    if err_params is not None:
        planner_value.save_error_model(out / "error_model.msgpack", err_params)
    atomic_write_text(out / "report.json", json.dumps(report, indent=1))
    b, a = report["value_before"], report["value_after"]
    log(f"value on held-out planner data, before -> after: R^2 candidates "
        f"{b['r2_candidates']:.3f} -> {a['r2_candidates']:.3f}, closed loop {b['r2_closed']:.3f}"
        f" -> {a['r2_closed']:.3f}; bias on candidates {b['bias_candidates']:+.3f} -> "
        f"{a['bias_candidates']:+.3f}; wrote {out}")
    return report


def run(cfg: AblationConfig, command: str = "", log=print) -> list[dict]:
    """Every variant of ``cfg`` (training the planner's value first where a row needs it);
    writes ``ablation.{json,md}`` to ``cfg.out`` after each variant."""
    code = code_version()  # the code this process runs: read now, not when a table is written
    out = pathlib.Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    variants = [v for v in cfg.variants.split(",") if v]
    name, _, run_dir = cfg.model.partition("=")
    value_dir = out / ("value" if cfg.value_collector == "short" else
                       f"value_{cfg.value_collector}")
    learned_file, error_file, bound = None, "", cfg.error_bound
    value_report = None
    if any(VARIANTS.index(v) >= VARIANTS.index("value") for v in variants):
        vcfg = dataclasses.replace(cfg.value, discount=cfg.discount,
                                   error_model=cfg.value.error_model or cfg.error_model)
        if not (value_dir / "report.json").is_file():
            log(f"training the value on the planner's own rollouts (the "
                f"'{cfg.value_collector}' planner)")
            collector = dataclasses.replace(variant_config(cfg, cfg.value_collector),
                                            out=str(value_dir))
            train_value(collector, vcfg, name, run_dir, value_dir, command, log, code)
        value_report = json.loads((value_dir / "report.json").read_text())
        _check_reused_value(value_report, vcfg, value_dir)
        learned_file = str(value_dir / "reward_value.msgpack")
        if cfg.error_model and (value_dir / "error_model.msgpack").is_file():
            error_file = str(value_dir / "error_model.msgpack")
        if not bound and "error" in variants:
            e_cl = (value_report.get("error_model") or {}).get("mean_error_closed_loop")
            if e_cl is None or not math.isfinite(e_cl) or e_cl <= 0:
                raise ValueError("error_bound=0 is calibrated on the error model's closed-loop "
                                 "error, which the value's report lacks: give --error-bound")
            bound = cfg.error_bound_scale * e_cl * math.sqrt(cfg.short_horizon)
    for variant in variants:
        t0 = time.perf_counter()
        closed_loop.run(variant_config(cfg, variant, learned_file, error_file, bound), command,
                        log)
        log(f"variant {variant}: {time.perf_counter() - t0:.0f} s")
        write(gather(out), cfg, command, out, bound, value_report, code)
    return gather(out)


def _check_reused_value(report: dict, want: planner_value.PlannerValueConfig,
                        value_dir: pathlib.Path) -> None:
    """A value trained by an earlier call is reused only if it was trained as this call asks
    (``--value.ensemble``, ``--value.worlds`` ...): a clear error names what differs. Settings the
    report predates count at their defaults."""
    fields = {f.name for f in dataclasses.fields(planner_value.PlannerValueConfig)}
    stored = (report.get("config") or {})
    had = dataclasses.replace(planner_value.PlannerValueConfig(),
                              **{k: v for k, v in stored.items() if k in fields})
    differ = [f"{k} {getattr(had, k)!r} (asked {getattr(want, k)!r})" for k in sorted(fields)
              if getattr(had, k) != getattr(want, k)]
    if differ:
        raise ValueError(f"{value_dir} holds a value trained with other settings: "
                         f"{'; '.join(differ)}. Use another --out, or delete that folder to "
                         f"train it again")


def gather(out: pathlib.Path) -> list[dict]:
    """The rows of every variant folder under ``out`` (also those of earlier calls, e.g. the
    rows split over two calls), each with its ``variant``, in :data:`VARIANTS` order."""
    rows = []
    for variant in VARIANTS:
        path = out / variant / "closed_loop.json"
        if path.is_file():
            rows += [dict(r, variant=variant) for r in json.loads(path.read_text())["rows"]]
    return rows


def write(rows: list[dict], cfg: AblationConfig, command: str, out: pathlib.Path,
          bound: float, value_report: dict | None, code: str | None = None) -> None:
    """``ablation.{json,md}`` of ``rows``; ``code``: the commit the run started from (default:
    the checkout's now)."""
    env = dict(command=command, backend=jax.default_backend(),
               device=jax.devices()[0].device_kind, jax=jax.__version__,
               code=code or code_version(),
               config=dataclasses.asdict(cfg), error_bound_used=bound)
    atomic_write_text(out / "ablation.json", json.dumps(
        dict(env=env, value=value_report, rows=rows), indent=1))
    variants = list(dict.fromkeys(r["variant"] for r in rows))
    scenarios = list(dict.fromkeys(r["scenario"] for r in rows))
    by = {(r["scenario"], r["variant"]): r for r in rows}

    def cell(r):
        if r is None:
            return "-"
        v = "-" if r["vel_rmse"] is None or np.isnan(r["vel_rmse"]) else f"{r['vel_rmse']:.3f}"
        return v + (f", fell at {r['fall_s']:.2f} s" if r["fell"] else "")

    lines = [f"# Dreamer-MPC ablation, {cfg.robot}, planner model {cfg.model}", "",
             f"Command: `{command}`", "",
             f"Device: {env['device']} ({env['backend']}), jax {env['jax']}, code {env['code']}. "
             f"K={cfg.mppi.samples}, {cfg.mppi.policy_samples} policy candidates; today's "
             f"planner H={cfg.mppi.horizon}, noise {cfg.planning.noise_std} rad around the plan; prior "
             f"{cfg.prior_fraction:.0%} of the noise candidates at {cfg.planning.prior_noise_std} rad; "
             f"short H={cfg.short_horizon}, gamma {cfg.discount}; error: {cfg.error_draws} "
             f"draws{' + learned one-step error' if cfg.error_model else ''}, cut at "
             f"{bound:.3f} m/s, weight {cfg.error_weight}. Variants up to error are cumulative; "
             f"prior_value is prior with the refitted value, discounted. The value's data: the "
             f"{cfg.value_collector} planner.", "",
             "Velocity RMSE (m/s) while upright:", "",
             "| scenario | " + " | ".join(variants) + " |",
             "|---|" + "---:|" * len(variants)]
    for sc in scenarios:
        lines.append(f"| {sc} | " + " | ".join(cell(by.get((sc, v))) for v in variants) + " |")
    lines += ["", "ms per control step / share of rollouts cut:", "",
              "| scenario | " + " | ".join(variants) + " |", "|---|" + "---:|" * len(variants)]
    for sc in scenarios:
        lines.append(f"| {sc} | " + " | ".join(
            f"{by[(sc, v)]['ms_per_step']:.1f} / {by[(sc, v)].get('cut_share', 0.0):.2f}"
            if (sc, v) in by else "-" for v in variants) + " |")
    if value_report:
        b, a = value_report["value_before"], value_report["value_after"]
        lines += ["", f"Value on the {cfg.value_collector} planner's held-out data "
                  f"({value_report['worlds']} worlds, "
                  f"{value_report['held_out_worlds']} held out), policy-trained -> refitted: "
                  f"R^2 on candidates {b['r2_candidates']:.3f} -> {a['r2_candidates']:.3f}, on "
                  f"the closed loop {b['r2_closed']:.3f} -> {a['r2_closed']:.3f}; bias V - G on "
                  f"candidates {b['bias_candidates']:+.3f} -> {a['bias_candidates']:+.3f}."]
        if "error_model" in value_report:
            e = value_report["error_model"]
            lines.append(f"One-step base-velocity error of the model: {e['mean_error_closed_loop']:.3f}"
                         f" m/s where the robot is, {e['mean_error_candidates']:.3f} m/s along the "
                         f"candidates; the error model's held-out R^2 {e['r2_held_out']:.3f}.")
    atomic_write_text(out / "ablation.md", "\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> None:
    config.config_main("python -m stride_jax.jobs.dreamer_mpc", AblationConfig, PRESETS, run,
                       argv, __doc__.split("\n")[0])


if __name__ == "__main__":
    stride_jax.set_xla_flags()  # before JAX starts: small CPUs deadlock without
    main()
