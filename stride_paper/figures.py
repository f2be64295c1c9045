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

and ``summary.json``: every number, plus the paper's claims side by side with ours
(:mod:`stride_paper.claims`).

This module holds the config, its presets and the driver; each figure family is a module of its
own (``figures_pendulum``: phase, allocation; ``figures_rollout``: nfe, horizon;
``figures_forces``), the runs they read are found or made by :mod:`stride_paper.figure_runs`, and
what the parts share is :mod:`stride_paper.figure_context`.

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
import time

from stride_jax.dynamics import models as models_lib
from stride_jax.io import atomic_write_text
from stride_paper import claims as claims_lib, figures_forces, figures_pendulum, figures_rollout
from stride_paper.figure_context import Context, device_text, json_default, split_names

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
      horizon_tables: Table I files (``results/table1/<robot>/table.json``) to read the horizon
        part's errors from instead of evaluating runs: the same numbers Table I shows, every seed.
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
    "paper": dict(out="results/reproduce/paper",
                  horizon_tables="results/table1/go1/table.json,results/table1/g1/table.json"),
}


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
    parts = split_names(cfg.parts)
    unknown = set(parts) - set(PARTS)
    if unknown:
        raise ValueError(f"unknown parts {sorted(unknown)}; available: {', '.join(PARTS)}")
    unknown = set(split_names(cfg.models)) - set(models_lib.MODELS)
    if unknown:
        raise ValueError(f"unknown models {sorted(unknown)}; available: "
                         f"{', '.join(models_lib.MODELS)}")
    tag = cfg.tag or preset
    out = pathlib.Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    ctx = Context(cfg, tag, out, pathlib.Path(cfg.root) / "reproduce_cache" / tag, command, log)
    path = out / "summary.json"
    summary = json.loads(path.read_text()) if path.is_file() else {}
    if summary.get("tag") != tag:
        summary = {}  # numbers of another preset are not mixed in
    summary.update(tag=tag, device=device_text(), config=dataclasses.asdict(cfg))
    summary.setdefault("commands", {})
    summary.setdefault("seconds", {})
    fns = {"phase": figures_pendulum.part_phase, "allocation": figures_pendulum.part_allocation,
           "nfe": figures_rollout.part_nfe, "horizon": figures_rollout.part_horizon,
           "forces": figures_forces.part_forces}
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
        summary.setdefault("devices", {})[name] = device_text()
        summary["device"] = _devices_text(summary["devices"])
        summary["commands"][name] = command
        summary["seconds"][name] = round(time.time() - t0, 1)
        summary["claims"] = claims_lib.claims(summary)
        atomic_write_text(path, json.dumps(summary, indent=1, default=json_default))
        log(f"== {name}: {summary['seconds'][name]:.0f} s")
    return summary
