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

This module is the driver; the config and its presets are :mod:`stride_paper.figures_config`
(re-exported here), each figure family is a module of its own (``figures_pendulum``: phase,
allocation; ``figures_rollout``: nfe, horizon; ``figures_forces``), the runs they read are found or made by :mod:`stride_paper.figure_runs`, and
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
from stride_paper.figures_config import PARTS, PRESETS, ReproduceConfig  # noqa: F401  (its face)


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
