"""Where the reproduction finds (or makes) its datasets and trained runs.

Layout under a root folder, the one ``experiments/table1.py`` writes:

    <root>/data/<robot>-<tag>/                 a dataset (``stride data``)
    <root>/runs/<robot>-<tag>/<model>-s<seed>/  a training run (``stride train``)

``tag`` is the preset's name (``tiny``, ``paper``), so runs of different sizes never mix. A run
that exists is reused: finished runs as they are, stopped ones resumed (when training is allowed)
or evaluated from their best checkpoint so far. Loading runs is the library's
(:mod:`stride_jax.eval.runs`).
"""

from __future__ import annotations

import pathlib
from typing import Callable

from stride_jax.eval.runs import is_finished, is_trained
from stride_jax.jobs import data as data_job, train as job


def data_dir(root: str | pathlib.Path, robot: str, tag: str) -> pathlib.Path:
    return pathlib.Path(root) / "data" / f"{robot}-{tag}"


def run_dir(root: str | pathlib.Path, robot: str, tag: str, model: str, seed: int
            ) -> pathlib.Path:
    return pathlib.Path(root) / "runs" / f"{robot}-{tag}" / f"{model}-s{seed}"


def ensure_data(path: pathlib.Path, robot: str, episodes: int, seconds: float, seed: int = 0,
                log: Callable[[str], None] = print) -> pathlib.Path:
    """The dataset at ``path``, generated (``stride data``, backend ``auto``) if absent."""
    if not (path / "meta.json").is_file():
        log(f"generating {path} ({robot}, {episodes} episodes x {seconds} s)")
        data_job.generate(data_job.DataConfig(robot=robot, episodes=episodes, seconds=seconds,
                                            seed=seed, out=str(path)))
    return path


def ensure_run(cfg: job.TrainConfig, train: bool, log: Callable[[str], None] = print
               ) -> pathlib.Path | None:
    """The run ``cfg.out``: reused when finished; trained (or resumed) when ``train``; reused
    from its best checkpoint so far when not; None if absent and not to be trained."""
    run = pathlib.Path(cfg.out)
    if is_finished(run):
        return run
    if train:
        log(f"training {cfg.model} on {cfg.robot} (seed {cfg.loop.seed}, {cfg.loop.steps} "
            f"steps) -> {run}")
        return job.run(cfg, log=log)
    return run if is_trained(run) else None
