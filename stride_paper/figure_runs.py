"""The trained runs each figure of ``experiments/reproduce.py`` reads: pendulum runs (trained
here when absent) and legged runs (``experiments/table1.py``'s; trained here only with
``train_legged``), laid out by :mod:`stride_paper.layout`."""

from __future__ import annotations

import dataclasses
import pathlib

from stride_jax.eval import horizon
from stride_jax.eval import runs as runs_lib
from stride_jax.jobs import train as job
from stride_paper import layout
from stride_paper.figure_context import Context, split_ints, split_names
from stride_paper.figures_config import ReproduceConfig


def pendulum_configs(cfg: ReproduceConfig, tag: str, robot: str, names) -> dict[str, list]:
    """The pendulum runs a part needs, ``{model: [TrainConfig per seed]}``."""
    data = layout.data_dir(cfg.root, robot, tag)
    preset = job.PRESETS[cfg.pendulum_train_preset]
    return {name: [dataclasses.replace(
                       preset, robot=robot, model=name, data=str(data),
                       loop=dataclasses.replace(preset.loop, seed=seed, steps=cfg.pendulum_steps),
                       out=str(layout.run_dir(cfg.root, robot, tag, name, seed)))
                   for seed in split_ints(cfg.pendulum_seeds)]
            for name in names}


def pendulum_jobs(cfg: ReproduceConfig, tag: str) -> list[job.TrainConfig]:
    """Every pendulum run the selected parts train (for training them side by side first)."""
    wanted = {"phase": ("pendulum", tuple(split_names(cfg.phase_models))),
              "allocation": ("pendulum_bouncing", ("stride",))}
    return [tc for part, (robot, names) in wanted.items() if part in split_names(cfg.parts)
            for tcs in pendulum_configs(cfg, tag, robot, names).values() for tc in tcs]


def ensure_pendulum_data(cfg: ReproduceConfig, tag: str, robot: str, log=print) -> pathlib.Path:
    return layout.ensure_data(layout.data_dir(cfg.root, robot, tag), robot,
                                cfg.pendulum_episodes, cfg.pendulum_seconds, log=log)


def pendulum_runs(ctx: Context, robot: str, names: tuple[str, ...]) -> dict[str, list]:
    """Pendulum runs (trained when absent), ``{model: [LoadedRun per seed]}``."""
    ensure_pendulum_data(ctx.cfg, ctx.tag, robot, ctx.log)
    return {name: [runs_lib.load_run(layout.ensure_run(tc, True, ctx.log)) for tc in tcs]
            for name, tcs in pendulum_configs(ctx.cfg, ctx.tag, robot, names).items()}


def legged_runs(ctx: Context, robot: str, names: list[str]) -> tuple[dict[str, list], list[str]]:
    """Legged runs ``{model: [LoadedRun per seed]}`` and the run folders that are missing."""
    c = ctx.cfg
    data = layout.data_dir(c.root, robot, ctx.tag)
    if c.train_legged:
        layout.ensure_data(data, robot, c.legged_episodes, c.legged_seconds, log=ctx.log)
    out, missing = {}, []
    for name in names:
        for seed in split_ints(c.seeds):
            path = layout.run_dir(c.root, robot, ctx.tag, name, seed)
            preset = job.PRESETS[c.legged_train_preset]
            steps = c.legged_steps or preset.loop.steps
            tc = dataclasses.replace(preset, robot=robot, model=name, data=str(data),
                                     loop=dataclasses.replace(preset.loop, seed=seed,
                                                              steps=steps),
                                     out=str(path))
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



def horizon_config(c: ReproduceConfig) -> horizon.HorizonConfig:
    return horizon.HorizonConfig(horizon=c.horizon, windows=c.windows, samples=c.samples,
                                 seed=c.seed)
