"""Reproduce the paper's figures and claims on our data (``experiments/reproduce.py``).

Parts (each a PNG and a JSON of its numbers in ``out``, with the command that made them):

* ``phase``: the pendulum's phase portrait near the upright, truth vs ONN, DeLaN, STRIDE
  (:mod:`~stride_jax.eval.phase`) -> ``phase_portrait.png``;
* ``allocation``: STRIDE's residual share in free swing vs at impacts on the bouncing pendulum
  (:mod:`~stride_jax.eval.allocation`) -> ``residual_allocation.png``;
* ``nfe``: rollout error and inference rate against NFE, CFM vs DDPM residual, Go1
  (:mod:`~stride_jax.eval.nfe`) -> ``nfe_tradeoff.png``;
* ``horizon``: rollout error vs horizon, five models, Go1 and G1
  (:mod:`~stride_jax.eval.horizon`) -> ``rollout_horizon.png``;
* ``forces``: predicted vs true vertical GRF per foot, Go1 per gait and G1
  (:mod:`~stride_jax.eval.contact`) -> ``contact_forces_<robot>.png``;

and ``summary.json``: every number, plus the paper's claims side by side with ours.

Runs come from ``<root>`` (layout in :mod:`~stride_paper.layout`): pendulum runs are trained
here when absent (minutes even at paper size); legged runs are the ones
``experiments/table1.py`` trains, and are trained here only when ``train_legged`` is set (the
``tiny`` preset). Everything is resumable: finished runs are reused, evaluations are cached in
``<root>/reproduce_cache`` per run, checkpoint and settings, and a part re-run alone updates its
entry of an existing summary.
"""

from __future__ import annotations

import dataclasses
import json
import pathlib
import platform
import time
from typing import Callable

import jax
import numpy as np

from stride_jax.dynamics import models as models_lib
from stride_jax.eval import allocation, contact, horizon, nfe, phase
from stride_jax.eval import runs as runs_lib
from stride_jax.io import atomic_write_text
from stride_jax.jobs import train as job
from stride_paper import layout

PARTS = ("phase", "allocation", "nfe", "horizon", "forces")


@dataclasses.dataclass(frozen=True)
class ReproduceConfig:
    """What ``experiments/reproduce.py`` runs (lists are comma-separated strings).

    Attributes:
      root: data and runs folder (``<root>/data``, ``<root>/runs``, ``<root>/reproduce_cache``).
      out: figures and numbers folder.
      tag: run folder suffix (``<robot>-<tag>``); empty means the preset's name.
      parts: which of phase, allocation, nfe, horizon, forces.
      robots: legged robots of the horizon and forces parts (nfe is Go1's).
      models: legged models.
      seeds: legged seeds.
      train_legged: train missing legged runs here (else: evaluate what exists; make them with
        ``experiments/table1.py``).
      legged_episodes, legged_seconds: a legged dataset to generate when training here
        (seconds 0: the robot's default).
      legged_train_preset, legged_steps: ``stride train`` preset and steps of legged runs
        (steps 0: the preset's).
      pendulum_episodes, pendulum_seconds, pendulum_train_preset, pendulum_steps,
        pendulum_seeds: the same for the pendulum and bouncing-pendulum runs.
      horizon_tables: Table I files (``results/<robot>/table.json``) to read the horizon part's
        errors from instead of evaluating runs: the same numbers Table I shows, every seed.
      horizon, windows, samples: rollout evaluation (steps, test windows, latent samples).
      nfe_flow, nfe_diffusion: NFE grids of the trade-off.
      timing_repeats: timed calls per inference rate (median).
      timing_batch: states per call of the batched inference rate.
      force_steps, force_window, force_samples: contact forces (steps per gait for the error,
        plotted steps, latent samples).
      phase_models: the pendulum models of the phase portrait.
      phase_grid, phase_worlds, phase_samples: phase portrait grid and draws per state.
      alloc_steps: held-out steps per region of the residual allocation.
      seed: evaluation draws.
    """

    root: str = "."
    out: str = "results/reproduce"
    tag: str = ""
    parts: str = ",".join(PARTS)
    robots: str = "go1,g1"
    models: str = ",".join(models_lib.MODELS)
    seeds: str = "0,1,2"
    train_legged: bool = False
    legged_episodes: int = 1024
    legged_seconds: float = 0.0
    legged_train_preset: str = "paper"
    legged_steps: int = 0
    pendulum_episodes: int = 512
    pendulum_seconds: float = 5.0
    pendulum_train_preset: str = "paper"
    pendulum_steps: int = 10000
    pendulum_seeds: str = "0,1,2"
    horizon_tables: str = ""
    horizon: int = 30
    windows: int = 256
    samples: int = 8
    nfe_flow: str = "1,2,4,8,16,32"
    nfe_diffusion: str = "1,2,4,8,16,32,64,100"
    timing_repeats: int = 20
    timing_batch: int = 256
    force_steps: int = 1024
    force_window: int = 100
    force_samples: int = 4
    phase_models: str = "onn,delan,stride"
    phase_grid: int = 21
    phase_worlds: int = 256
    phase_samples: int = 128
    alloc_steps: int = 2048
    seed: int = 0


PRESETS = {
    # CPU, CI-sized: every part end to end on tiny data and models (numbers are not the paper's).
    "tiny": dict(out="results/reproduce/tiny", seeds="0,1", train_legged=True,
                 legged_episodes=8, legged_seconds=2.0, legged_train_preset="tiny",
                 legged_steps=100, pendulum_episodes=24, pendulum_seconds=4.0,
                 pendulum_train_preset="tiny", pendulum_steps=600, pendulum_seeds="0",
                 windows=16, samples=2, nfe_flow="1,4", nfe_diffusion="1,4,10",
                 timing_repeats=20, force_steps=64, force_window=40, force_samples=2,
                 phase_grid=11, phase_worlds=32, phase_samples=16, alloc_steps=256),
    # GPU: legged runs from `experiments/table1.py --preset paper` under the same root; the
    # horizon part reads Table I's own numbers (every seed) from the committed tables.
    "paper": dict(out="results/reproduce/paper", horizon_tables="results/go1/table.json,results/g1/table.json"),
}


def _ints(s: str) -> list[int]:
    return [int(x) for x in s.split(",") if x.strip()]


def _names(s: str) -> list[str]:
    return [x.strip() for x in s.split(",") if x.strip()]


def _device() -> str:
    d, host = jax.devices()[0], platform.processor() or platform.machine()
    return f"{d.device_kind} ({jax.default_backend()}; {host})"


@dataclasses.dataclass(frozen=True)
class _Ctx:
    cfg: ReproduceConfig
    tag: str
    out: pathlib.Path
    cache: pathlib.Path
    command: str
    log: Callable[[str], None]

    def title(self, what: str) -> str:
        return f"{what}\n`{self.command}` ({self.tag} runs; {_device()})"

    def write(self, name: str, numbers: dict) -> None:
        atomic_write_text(self.out / f"{name}.json", json.dumps(
            {"command": self.command, "preset_tag": self.tag, "device": _device(),
             **numbers}, indent=1, default=_json_default))


def _json_default(x):
    if isinstance(x, (np.floating, np.integer)):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    raise TypeError(f"not JSON serialisable: {type(x)}")


# ---------------------------------------------------------------------------------------- runs

def pendulum_configs(cfg: ReproduceConfig, tag: str, robot: str, names) -> dict[str, list]:
    """The pendulum runs a part needs, ``{model: [TrainConfig per seed]}``."""
    data = layout.data_dir(cfg.root, robot, tag)
    return {name: [job.TrainConfig(**dict(job.PRESETS[cfg.pendulum_train_preset], robot=robot,
                                          model=name, seed=seed, steps=cfg.pendulum_steps,
                                          data=str(data),
                                          out=str(layout.run_dir(cfg.root, robot, tag, name,
                                                                   seed))))
                   for seed in _ints(cfg.pendulum_seeds)]
            for name in names}


def pendulum_jobs(cfg: ReproduceConfig, tag: str) -> list[job.TrainConfig]:
    """Every pendulum run the selected parts train (for training them side by side first)."""
    wanted = {"phase": ("pendulum", tuple(_names(cfg.phase_models))),
              "allocation": ("pendulum_bouncing", ("stride",))}
    return [tc for part, (robot, names) in wanted.items() if part in _names(cfg.parts)
            for tcs in pendulum_configs(cfg, tag, robot, names).values() for tc in tcs]


def ensure_pendulum_data(cfg: ReproduceConfig, tag: str, robot: str, log=print) -> pathlib.Path:
    return layout.ensure_data(layout.data_dir(cfg.root, robot, tag), robot,
                                cfg.pendulum_episodes, cfg.pendulum_seconds, log=log)


def _pendulum_runs(ctx: _Ctx, robot: str, names: tuple[str, ...]) -> dict[str, list]:
    """Pendulum runs (trained when absent), ``{model: [LoadedRun per seed]}``."""
    ensure_pendulum_data(ctx.cfg, ctx.tag, robot, ctx.log)
    return {name: [runs_lib.load_run(layout.ensure_run(tc, True, ctx.log)) for tc in tcs]
            for name, tcs in pendulum_configs(ctx.cfg, ctx.tag, robot, names).items()}


def _legged_runs(ctx: _Ctx, robot: str, names: list[str]) -> tuple[dict[str, list], list[str]]:
    """Legged runs ``{model: [LoadedRun per seed]}`` and the run folders that are missing."""
    c = ctx.cfg
    data = layout.data_dir(c.root, robot, ctx.tag)
    if c.train_legged:
        layout.ensure_data(data, robot, c.legged_episodes, c.legged_seconds, log=ctx.log)
    out, missing = {}, []
    for name in names:
        for seed in _ints(c.seeds):
            path = layout.run_dir(c.root, robot, ctx.tag, name, seed)
            preset = dict(job.PRESETS[c.legged_train_preset])
            if c.legged_steps:
                preset["steps"] = c.legged_steps
            tc = job.TrainConfig(**dict(preset, robot=robot, model=name, seed=seed,
                                        data=str(data), out=str(path)))
            run = layout.ensure_run(tc, c.train_legged, ctx.log)
            if run is None:
                missing.append(str(path))
                continue
            out.setdefault(name, []).append(runs_lib.load_run(run))
    if missing:
        ctx.log(f"{len(missing)} {robot} runs missing (make them with `python "
                f"experiments/table1.py --robot {robot} --preset {ctx.tag} --root {c.root}`): "
                f"{', '.join(missing)}")
    return out, missing


def _hcfg(c: ReproduceConfig) -> horizon.HorizonConfig:
    return horizon.HorizonConfig(horizon=c.horizon, windows=c.windows, samples=c.samples,
                                 seed=c.seed)


# --------------------------------------------------------------------------------------- parts

def part_phase(ctx: _Ctx) -> dict:
    c = ctx.cfg
    names = tuple(_names(c.phase_models))
    runs = _pendulum_runs(ctx, "pendulum", names)
    pcfg = phase.PhaseConfig(grid=c.phase_grid, worlds=c.phase_worlds, samples=c.phase_samples,
                             seed=c.seed)
    per_seed = []
    for i in range(len(next(iter(runs.values())))):
        numbers, arrays = phase.evaluate({n: rs[i] for n, rs in runs.items()}, pcfg)
        per_seed.append(numbers)
        if i == 0:
            phase.plot(arrays, numbers, ctx.out / "phase_portrait.png",
                       ctx.title("Pendulum near the upright (seed 0)"))
    agg = {}
    for name in names:
        agg[name] = {k: {"mean": float(np.mean([p[name][k] for p in per_seed])),
                         "std": float(np.std([p[name][k] for p in per_seed])),
                         "n": len(per_seed)}
                     for k in ("field_rmse", "field_rmse_normalised", "w1_near",
                               "w1_near_over_floor", "spread_near")}
        agg[name]["steps_done"] = sorted({p[name]["steps_done"] for p in per_seed}, key=str)
    result = {"truth": per_seed[0]["truth"], "models": agg, "per_seed": per_seed,
              "residual": phase.RESIDUAL,
              "config": dataclasses.asdict(pcfg), "figure": "phase_portrait.png"}
    ctx.write("phase", result)
    return result


def part_allocation(ctx: _Ctx) -> dict:
    c = ctx.cfg
    runs = _pendulum_runs(ctx, "pendulum_bouncing", ("stride",))["stride"]
    acfg = allocation.AllocationConfig(steps=c.alloc_steps, samples=c.samples, seed=c.seed)
    per_seed, first = [], None
    for run in runs:
        numbers, arrays = allocation.evaluate(run, acfg)
        per_seed.append(numbers)
        first = first or arrays
    agg = allocation.over_seeds(per_seed)
    allocation.plot(agg, first, ctx.out / "residual_allocation.png",
                    ctx.title("Residual allocation (STRIDE, bouncing pendulum)"))
    result = {"share": agg, "per_seed": per_seed, "definition": allocation.__doc__.strip(),
              "config": dataclasses.asdict(acfg), "figure": "residual_allocation.png"}
    ctx.write("allocation", result)
    return result


def part_nfe(ctx: _Ctx) -> dict:
    c = ctx.cfg
    names = [n for n in ("stride", "lnn_diffusion", "delan") if n in _names(c.models)]
    runs, missing = _legged_runs(ctx, "go1", names)
    hcfg = _hcfg(c)
    curves = {}
    for name, grid in (("stride", c.nfe_flow), ("lnn_diffusion", c.nfe_diffusion)):
        if runs.get(name):
            ctx.log(f"NFE sweep: {name} on go1 ({len(runs[name])} seeds)")
            curves[name] = nfe.sweep(runs[name], _ints(grid), hcfg, ctx.cache,
                                     c.timing_repeats, c.timing_batch, ctx.log)
    reference = None
    if runs.get("delan"):
        per_seed = [horizon.evaluate(r, hcfg, ctx.cache) for r in runs["delan"]]
        cums = [p["cumulative"] for p in per_seed]
        reference = {"error_mean": float(np.mean(cums)), "error_std": float(np.std(cums)),
                     **nfe.rates(runs["delan"][0], None, c.timing_repeats, c.timing_batch),
                     "seeds": [r.seed for r in runs["delan"]]}
    if curves:
        nfe.plot(curves, reference, ctx.out / "nfe_tradeoff.png", jax.devices()[0].device_kind,
                 ctx.title(f"Go1: CFM vs DDPM residual, H = {c.horizon}"))
    result = {"curves": curves, "delan": reference, "missing_runs": missing,
              "horizon": dataclasses.asdict(hcfg), "definition": nfe.__doc__.strip(),
              "device": _device(), "figure": "nfe_tradeoff.png" if curves else None}
    ctx.write("nfe", result)
    return result


def part_horizon(ctx: _Ctx) -> dict:
    c = ctx.cfg
    hcfg = _hcfg(c)
    table, per_run, missing, sources = {}, {}, [], {}
    tables = dict(horizon.from_table(p) for p in _names(c.horizon_tables))
    for robot in _names(c.robots):
        if robot in tables:
            ctx.log(f"rollout errors on {robot}: read from its Table I file")
            per_run[robot], sources[robot] = tables[robot], "table"
        else:
            runs, miss = _legged_runs(ctx, robot, _names(c.models))
            missing += miss
            per_run[robot], sources[robot] = {}, "evaluated"
            for name, rs in runs.items():
                ctx.log(f"rollout errors: {name} on {robot} ({len(rs)} seeds)")
                per_run[robot][name] = [horizon.evaluate(r, hcfg, ctx.cache) for r in rs]
        table[robot] = {}
        for name, results in per_run[robot].items():
            if name not in _names(c.models):
                continue
            row = horizon.over_seeds(results)
            ph = np.asarray(row["per_horizon_mean"])
            row["growth_last_over_half"] = float(ph[-1] / ph[len(ph) // 2 - 1])
            table[robot][name] = row
    table = {r: t for r, t in table.items() if t}
    if table:
        horizon.plot(table, ctx.out / "rollout_horizon.png",
                     ctx.title("Open-loop rollout error vs horizon (mean ± std over seeds"
                               + ("; from " + ", ".join(_names(c.horizon_tables))
                                  if "table" in sources.values() else "") + ")"))
    result = {"table": table, "per_run": per_run, "missing_runs": missing, "source": sources,
              "tables": _names(c.horizon_tables),
              "config": dataclasses.asdict(hcfg), "definition": horizon.__doc__.strip(),
              "figure": "rollout_horizon.png" if table else None}
    ctx.write("horizon", result)
    return result


def part_forces(ctx: _Ctx) -> dict:
    c = ctx.cfg
    fcfg = contact.ContactConfig(steps=c.force_steps, window=c.force_window,
                                 samples=c.force_samples, seed=c.seed)
    names = [n for n in _names(c.models) if models_lib.MODELS[n][0] == "structured"]
    result = {"config": dataclasses.asdict(fcfg), "definition": contact.__doc__.strip(),
              "robots": {}, "missing_runs": []}
    for robot in _names(c.robots):
        runs, missing = _legged_runs(ctx, robot, names)
        result["missing_runs"] += missing
        if not runs:
            continue
        behaviours = contact.behaviours(robot, next(iter(runs.values()))[0].ds.arrays)[0]
        numbers, arrays, per_model = {}, {}, {}
        for name, rs in runs.items():
            ctx.log(f"contact forces: {name} on {robot} ({len(rs)} seeds)")
            per_seed = []
            for i, run in enumerate(rs):
                key = runs_lib.cache_key(run, **dataclasses.asdict(fcfg))
                path = ctx.cache / "forces" / f"{run.path.parent.name}_{run.path.name}.json"
                if i == 0:  # the plotted run: its arrays are needed, so no cache
                    num, arr = contact.evaluate(run, fcfg)
                    arrays[name] = arr
                else:
                    num = runs_lib.cached(path, key, lambda run=run: contact.evaluate(run, fcfg)[0])
                per_seed.append(num)
            per_model[name] = per_seed
            numbers[name] = contact.over_seeds(per_seed, behaviours)
        png = f"contact_forces_{robot}.png"
        contact.plot(robot, arrays, {n: ps[0] for n, ps in per_model.items()}, ctx.out / png,
                     ctx.title(f"{robot}: vertical GRF from the residual (seed 0; legend: "
                               "mean |error| of that behaviour)"))
        result["robots"][robot] = {"table": numbers, "per_seed": per_model, "figure": png}
    ctx.write("forces", result)
    return result


# ------------------------------------------------------------------------------------- claims

def _dig(d, *path):
    for k in path:
        if not isinstance(d, dict) or d.get(k) is None:
            return None
        d = d[k]
    return d


# The paper's Table I (H = 30): state RMSE and force error (N) per robot and model.
PAPER_TABLE = {
    "go1": {"onn": (5.489, None), "diffusion": (3.521, None), "delan": (1.326, 9.4),
            "lnn_diffusion": (1.154, 8.8), "stride": (0.932, 6.7)},
    "g1": {"onn": (1.204, None), "diffusion": (0.314, None), "delan": (1.023, 17.1),
           "lnn_diffusion": (0.918, 15.4), "stride": (0.289, 12.1)},
}
# Where the paper's text gives a different reduction than its table implies (Sec. IV-D).
PAPER_TEXT = {("g1", "onn"): "text: 53% lower (ratio 0.47)",
              ("g1", "lnn_diffusion"): "text: 21% lower (ratio 0.79)",
              ("go1", "onn"): "text: 83% lower", ("go1", "lnn_diffusion"): "text: 19% lower"}


def claims(summary: dict) -> list[dict]:
    """The paper's claims next to ours. ``holds``: whether ours meets the criterion the claim
    states (None: not measured). A verdict on tiny-preset numbers says nothing about the paper."""
    out = []

    def add(cid, claim, paper, ours, holds, where):
        out.append({"id": cid, "claim": claim, "paper": paper, "ours": ours,
                    "holds": None if ours is None else bool(holds), "where": where})

    ratio = lambda a, b: a / b if a is not None and b else None
    h = _dig(summary, "horizon", "table") or {}
    for robot, t in h.items():
        s = _dig(t, "stride", "cumulative_mean")
        paper = PAPER_TABLE.get(robot, {})
        for other in ("onn", "diffusion", "delan", "lnn_diffusion"):
            if other not in t:
                continue
            r = ratio(s, _dig(t, other, "cumulative_mean"))
            p = ratio(paper.get("stride", (None,))[0], paper.get(other, (None,))[0])
            add(f"state_{robot}_vs_{other}", f"{robot}: STRIDE / {other} cumulative state error "
                f"(H = {len(t[other]['per_horizon_mean'])}; < 1: STRIDE better)",
                {"table": p, "note": PAPER_TEXT.get((robot, other))}, r,
                r is not None and r < 1, "horizon")
        others = [_dig(t, m, "cumulative_mean") for m in t if m != "stride"]
        others = [o for o in others if o]
        if s is not None and others:
            r = s / min(others)
            add(f"abstract_20pct_state_{robot}", f"{robot}: STRIDE at least 20% below the best "
                "baseline in long-horizon error (abstract; ratio <= 0.80)",
                "<= 0.80", r, r <= 0.8, "horizon")
        g_onn, g_delan = (_dig(t, m, "growth_last_over_half") for m in ("onn", "delan"))
        if g_onn is not None and g_delan is not None:
            add(f"growth_{robot}", f"{robot}: ONN's error grows faster than DeLaN's "
                "(error at H over error at H/2: ONN, DeLaN; 2 is linear growth from zero)",
                "ONN near-exponential, DeLaN ~linear", [g_onn, g_delan], g_onn > g_delan,
                "horizon")
    f = _dig(summary, "forces", "robots") or {}
    paper_rel = {"go1": 0.13, "g1": 0.08}
    for robot, t in f.items():
        s = _dig(t, "table", "stride", "overall", "mean")
        paper = PAPER_TABLE.get(robot, {})
        for other in ("delan", "lnn_diffusion"):
            r = ratio(s, _dig(t, "table", other, "overall", "mean"))
            add(f"force_{robot}_vs_{other}", f"{robot}: STRIDE / {other} foot-force error "
                "(< 1: STRIDE better; the paper: ~30% below DeLaN)",
                ratio(paper.get("stride", (0, None))[1], paper.get(other, (0, None))[1]), r,
                r is not None and r < 1, "forces")
        r = ratio(s, _dig(t, "table", "delan", "overall", "mean"))
        add(f"abstract_20pct_force_{robot}", f"{robot}: STRIDE's force error at least 20% below "
            "DeLaN's (abstract; ratio <= 0.80)", "<= 0.80", r, r is not None and r <= 0.8,
            "forces")
        rel = _dig(t, "table", "stride", "overall", "relative_mean")
        add(f"force_relative_{robot}", f"{robot}: STRIDE's force error / mean stance force "
            "(holds: at most the paper's)", paper_rel.get(robot), rel,
            rel is not None and rel <= paper_rel.get(robot, 0), "forces")
    n = summary.get("nfe") or {}
    curves, ref = n.get("curves") or {}, n.get("delan")
    if "stride" in curves and "lnn_diffusion" in curves:
        fl, df = curves["stride"], curves["lnn_diffusion"]
        common = sorted(set(fl["nfe"]) & set(df["nfe"]))
        hz = lambda c, k: c["residual_batch_hz"][c["nfe"].index(k)]
        add("nfe_rate", f"CFM samples faster than DDPM at every common NFE (residual sampler "
            f"calls/s, {fl['batch']} states per call: CFM, DDPM)", True,
            {str(k): [hz(fl, k), hz(df, k)] for k in common} or None,
            all(hz(fl, k) > hz(df, k) for k in common), "nfe")
        # The paper's point: the flow needs fewer evaluations for the same accuracy. Each
        # sampler at its smallest NFE within 5% of its own best error: which is faster there?
        def settled(c):
            errs = [e if e is not None and np.isfinite(e) else np.inf for e in c["error_mean"]]
            best = min(errs)
            k = next(k for k, e in zip(c["nfe"], errs) if e <= 1.05 * best)
            return k, errs[c["nfe"].index(k)], hz(c, k)
        if all(np.isfinite(min([e if e is not None else np.inf for e in c["error_mean"]]))
               for c in (fl, df)):
            (ka, ea, ra), (kb, eb, rb) = settled(fl), settled(df)
            add("nfe_matched", "at the smallest NFE within 5% of its own best rollout error, CFM "
                "samples faster than DDPM ([NFE, error, calls/s]: CFM, DDPM)", "CFM faster",
                [[ka, ea, ra], [kb, eb, rb]], ra > rb, "nfe")
        if ref is not None:
            first = lambda c: next((k for k, e in zip(c["nfe"], c["error_mean"])
                                    if e <= ref["error_mean"]), None)
            a, b = first(fl), first(df)
            add("nfe_delan_level", "CFM reaches DeLaN's rollout error with fewer NFEs than DDPM "
                "(smallest NFE at or below DeLaN's error: CFM, DDPM; None: never)",
                "CFM < DDPM", [a, b], a is not None and (b is None or a < b), "nfe")
    a = _dig(summary, "allocation", "share") or {}
    free, hit = _dig(a, "free", "mean"), _dig(a, "contact", "mean")
    add("allocation_split", "residual share lower in free swing than at impacts (free, impacts)",
        [0.065, 0.788], [free, hit] if free is not None and hit is not None else None,
        free is not None and hit is not None and free < hit, "allocation")
    add("allocation_free", "residual share in free swing small (holds: <= 0.15)", 0.065, free,
        free is not None and free <= 0.15, "allocation")
    add("allocation_contact", "residual share at impacts large (holds: >= 0.5)", 0.788, hit,
        hit is not None and hit >= 0.5, "allocation")
    ph = _dig(summary, "phase", "models") or {}
    s = _dig(ph, "stride", "w1_near", "mean")
    for other in ("delan", "onn"):
        o = _dig(ph, other, "w1_near", "mean")
        add(f"phase_w1_vs_{other}", f"pendulum near upright: STRIDE's one-step distribution "
            f"closer to the truth than {other}'s (W1 ratio; < 1: closer)", "< 1 (qualitative)",
            ratio(s, o), s is not None and o and s < o, "phase")
    floor = _dig(ph, "stride", "w1_near_over_floor", "mean")
    add("phase_beats_any_deterministic", "pendulum near upright: STRIDE's W1 below the floor of "
        "every deterministic model (W1 / floor < 1)", "(implied by multimodality)", floor,
        floor is not None and floor < 1, "phase")
    return out


# ---------------------------------------------------------------------------------------- main

def _devices_text(devices: dict[str, str]) -> str:
    """``"phase, nfe: <device>; horizon: <device>"`` (parts run on different machines)."""
    by: dict[str, list[str]] = {}
    for part, dev in devices.items():
        by.setdefault(dev, []).append(part)
    if len(by) == 1:
        return next(iter(by))
    return "; ".join(f"{', '.join(parts)}: {dev}" for dev, parts in by.items())


def run(cfg: ReproduceConfig, preset: str, command: str, log=print) -> dict:
    """Runs the selected parts, writes their figures and JSON, and updates ``summary.json``."""
    parts = _names(cfg.parts)
    unknown = set(parts) - set(PARTS)
    if unknown:
        raise ValueError(f"unknown parts {sorted(unknown)}; available: {', '.join(PARTS)}")
    unknown = set(_names(cfg.models)) - set(models_lib.MODELS)
    if unknown:
        raise ValueError(f"unknown models {sorted(unknown)}; available: "
                         f"{', '.join(models_lib.MODELS)}")
    tag = cfg.tag or preset
    out = pathlib.Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    ctx = _Ctx(cfg, tag, out, pathlib.Path(cfg.root) / "reproduce_cache" / tag, command, log)
    path = out / "summary.json"
    summary = json.loads(path.read_text()) if path.is_file() else {}
    if summary.get("tag") != tag:
        summary = {}  # numbers of another preset are not mixed in
    summary.update(tag=tag, device=_device(), config=dataclasses.asdict(cfg))
    summary.setdefault("commands", {})
    summary.setdefault("seconds", {})
    fns = {"phase": part_phase, "allocation": part_allocation, "nfe": part_nfe,
           "horizon": part_horizon, "forces": part_forces}
    for name in parts:
        t0 = time.time()
        log(f"== {name}")
        result = fns[name](ctx)
        if "robots" in result and isinstance(summary.get(name), dict):
            # A part re-run for some robots keeps the others' numbers (one device call each).
            kept = {r: v for r, v in summary[name].get("robots", {}).items()
                    if r not in result["robots"]}
            result["robots"] = {**kept, **result["robots"]}
        summary[name] = result
        summary.setdefault("devices", {})[name] = _device()
        summary["device"] = _devices_text(summary["devices"])
        summary["commands"][name] = command
        summary["seconds"][name] = round(time.time() - t0, 1)
        summary["claims"] = claims(summary)
        atomic_write_text(path, json.dumps(summary, indent=1, default=_json_default))
        log(f"== {name}: {summary['seconds'][name]:.0f} s")
    return summary
