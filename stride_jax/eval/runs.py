"""Trained runs as the evaluation sees them: whether a run folder (``stride train``) is trained
or finished, loading it with its dataset, and caching an evaluation's numbers per checkpoint.

Evaluation never trains: where runs are made for a reproduction is the paper package's business
(``stride_paper.layout``).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import pathlib
from typing import Any, Callable

import numpy as np

from stride_jax.dynamics import checkpoint, models
from stride_jax.io import atomic_write_text
from stride_jax.sim import dataset
from stride_jax.types import ModelSpec


def is_trained(run: pathlib.Path) -> bool:
    """A run with a definition and a best checkpoint (finished or not)."""
    return (run / "model.json").is_file() and (run / "summary.json").is_file()


def is_finished(run: pathlib.Path) -> bool:
    return is_trained(run) and bool(json.loads((run / "summary.json").read_text()).get(
        "finished"))


@functools.lru_cache(maxsize=4)
def load_dataset(path: str) -> dataset.Dataset:
    """A dataset, loaded (and checksummed) once per process: runs of one robot share it."""
    return dataset.load(path)


@dataclasses.dataclass(frozen=True, eq=False)
class LoadedRun:
    """A trained run with what its evaluation needs.

    Attributes:
      path: the run folder.
      model, params: the model and its best parameters (``stride_jax.dynamics.load``).
      ds: the dataset it was trained on.
      spec: the model spec.
      seed: training seed.
      nfe: the residual's trained evaluations per sample (None for deterministic models).
      best_step, steps_done, finished: from ``summary.json``.
    """

    path: pathlib.Path
    model: models.Model
    params: Any
    ds: dataset.Dataset
    spec: ModelSpec
    seed: int
    nfe: int | None
    best_step: int
    steps_done: int
    finished: bool

    @property
    def robot(self) -> str:
        return self.ds.meta["robot"]


def train_seed(train: dict) -> int:
    """The training seed in a run's ``config.json`` ``train`` entry: ``loop.seed``, or the flat
    ``seed`` of runs trained before ``stride train`` nested the loop's settings."""
    return int(train["loop"]["seed"] if "loop" in train else train["seed"])


def load_run(run: str | pathlib.Path) -> LoadedRun:
    run = pathlib.Path(run)
    model, params = checkpoint.load(run)
    cfg = json.loads((run / "config.json").read_text())
    summary = json.loads((run / "summary.json").read_text())
    ds = load_dataset(str(pathlib.Path(cfg["dataset"]).absolute()))
    nfe = json.loads((run / "model.json").read_text())["config"]["nfe"] if model.stochastic \
        else None
    return LoadedRun(run, model, params, ds, models.spec_from_meta(ds.meta),
                     train_seed(cfg["train"]), nfe, summary.get("best_step"),
                     summary.get("steps_done"),
                     bool(summary.get("finished")))


def cache_key(run: LoadedRun, **settings) -> dict:
    """What an evaluation of ``run`` depends on: its checkpoint and the settings."""
    return {"run": str(run.path.absolute()), "best_step": run.best_step, **settings}


def cached(path: pathlib.Path, key: dict, compute: Callable[[], dict]) -> dict:
    """``compute()``, stored at ``path`` with ``key`` and reused while the key matches."""
    if path.is_file():
        saved = json.loads(path.read_text())
        if saved.get("key") == key:
            return saved["result"]
    result = compute()
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, json.dumps({"key": key, "result": result}, indent=1))
    return result


def valid_steps(split: dict, n: int, seed: int, mask: np.ndarray | None = None) -> np.ndarray:
    """``[<=n, 2]`` random (episode, step) pairs of valid steps (and of ``mask [E, T]``)."""
    ok = split["valid"] if mask is None else split["valid"] & mask
    idx = np.argwhere(ok)
    return idx[np.random.default_rng(seed).permutation(len(idx))[:n]]
