"""A dynamics model trained on a dataset: the dataset's transitions as flat examples and
:func:`stride_jax.train.loop.run` on their per-example loss, keeping the parameters with the
best validation ``select`` part of the loss.

* :func:`examples` -- consecutive valid steps of a dataset split as flat examples (the step's
  ``q, qd, tau, qdd, ctrl``, the next step's ``q, qd``, the feet's contact Jacobians and, on
  sloped data, gravity's direction);
* :func:`train` -- a model on a dataset's train and validation splits (``stride train``);
* :func:`train_examples` -- a model on examples given directly (``stride_jax.train.fit``: a
  robot known only from arrays), writing ``summary.json`` beside the run's checkpoints;
* :func:`train_side_by_side` -- the same for several seeds in one program (``stride train
  --seeds``), each seed its own run folder.

The loop itself (minibatches, checkpoints, resumption, the CSV log) is
:mod:`stride_jax.train.loop`'s, shared with every other model trained with optax here.
"""

from __future__ import annotations

import json
import pathlib
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from stride_jax import distributed
from stride_jax.dynamics.checkpoint import params_sha256
from stride_jax.io import atomic_write_text
from stride_jax.sim import record
from stride_jax.train.loop import LoopConfig, TrainingError, optimizer, run, run_many


VALIDATION_CHUNK = 256  # validation examples evaluated at once (``train_examples``)


def examples(split: dict, jacobians: Callable | None = None) -> dict:
    """Transitions between consecutive valid steps as flat examples [N, ...]: the step's
    ``q, qd, tau, qdd, ctrl``, the next step's ``q_next, qd_next``, and ``contact_jac``
    ``[N, nfeet * k, nv]``, the sole Jacobians of the feet in contact (zero rows for feet in
    swing; training-time supervision only, see ``stride.loss``), and ``down`` ``[N, 3]``,
    gravity's direction at the step, where the split's gravity is tilted somewhere
    (:func:`stride_jax.sim.record.down_of`; sloped data).

    ``jacobians(q [N, nq]) -> [N, nfeet, k, nv]`` (``eval.forces.foot_jacobians``); without it
    (robots without feet) ``contact_jac`` has no rows.
    """
    v = split["valid"][:, :-1] & split["valid"][:, 1:]
    ex = {k: split[k][:, :-1][v] for k in ("q", "qd", "tau", "qdd", "ctrl")}
    n, nv = len(ex["q"]), split["qd"].shape[-1]
    feet = split.get("foot_contact")
    if jacobians is None or feet is None or feet.shape[-1] == 0:
        jac = np.zeros((n, 0, nv), np.float32)
    else:
        stance = feet[:, :-1][v] > 0.5  # [N, nfeet]
        jac = np.zeros((n, feet.shape[-1], 0, nv), np.float32)
        if stance.any():
            some = stance.any(-1)
            j = np.asarray(jacobians(ex["q"][some]), np.float32)
            jac = np.zeros((n,) + j.shape[1:], np.float32)
            jac[some] = j * stance[some][:, :, None, None]
        jac = jac.reshape(n, -1, nv)
    ex.update(q_next=split["q"][:, 1:][v], qd_next=split["qd"][:, 1:][v], contact_jac=jac)
    down = record.down_of(split)
    if down is not None:  # sloped episodes: the models are told each example's gravity
        ex["down"] = down[:, :-1][v]
    ex = {k: np.asarray(a, np.float32) for k, a in ex.items()}
    bad = {k: int((~np.isfinite(a.reshape(len(a), -1))).any(-1).sum()) for k, a in ex.items()}
    if any(bad.values()):
        raise TrainingError(f"non-finite values in valid dataset steps ({bad}); regenerate the "
                            "dataset with this version, which marks such steps invalid")
    return ex


def train(loss_fn: Callable, init_fn: Callable, train_split: dict, val_split: dict,
          cfg: LoopConfig, out: pathlib.Path, log: Callable[[str], None] = print,
          jacobians: Callable | None = None, batch_loss: Callable | None = None) -> dict:
    """Trains ``init_fn(key)`` params on ``loss_fn(params, example, key)``; returns the best params.

    Writes ``out/ckpt`` (latest, resumable), ``out/best`` (lowest validation ``select`` part of
    the loss where it has one, else the lowest validation loss) and
    ``out/metrics.csv``; resumes from ``out/ckpt`` when it exists. ``jacobians``: see
    :func:`examples`; ``batch_loss``: see :func:`train_examples`.
    """
    data, val = examples(train_split, jacobians), examples(val_split, jacobians)
    return train_examples(loss_fn, init_fn, data, val, cfg, out, log, batch_loss)


def train_examples(loss_fn: Callable, init_fn: Callable, data: dict, val: dict,
                   cfg: LoopConfig, out: pathlib.Path, log: Callable[[str], None] = print,
                   batch_loss: Callable | None = None) -> dict:
    """:func:`train` on flat examples ``{name: [N, ...]}`` (``q, qd, tau, qdd``, and whatever
    else ``loss_fn`` reads) for training and validation: :func:`run` with :func:`optimizer`.
    ``loss_fn(params, example, key) -> (loss, parts)`` is for one example; ``batch_loss(params,
    examples, keys) -> (mean loss, mean parts)``, where given, is a training minibatch's loss
    instead of ``loss_fn``'s mean (``Model.batch_loss``; validation stays ``loss_fn``'s mean).
    ``out/summary.json`` records the best step and the SHA-256 of its parameters
    (``checkpoint.params_sha256``)."""
    out = pathlib.Path(out)
    out.mkdir(parents=True, exist_ok=True)
    mean_loss, validate, _ = _objective(loss_fn, data, val, batch_loss)
    key_init, key_loop = seed_keys(cfg.seed)
    res = run(mean_loss, init_fn(key_init), data, cfg, optimizer(cfg.lr, cfg.steps), key_loop,
              validate, out, log)
    if distributed.is_main():
        _write_summary(out, res, cfg)
        log(_time_split(res))
    return res.params


def train_side_by_side(loss_fn: Callable, init_fn: Callable, data: dict, val: dict, cfg: LoopConfig,
                       runs: dict[int, pathlib.Path], log: Callable[[str], None] = print,
                       batch_loss: Callable | None = None) -> dict[int, dict]:
    """:func:`train_examples` for several seeds at once, side by side in one program
    (:func:`stride_jax.train.loop.run_many`): ``runs`` maps each seed to its run folder, and each
    folder ends as :func:`train_examples` with ``cfg.seed`` = that seed leaves it (the same
    initialisation and minibatch draws; a single run into the folder resumes it). Returns each
    seed's best parameters."""
    if not runs:
        raise ValueError("train_side_by_side: no seeds to train")
    outs = [pathlib.Path(o) for o in runs.values()]
    if len(set(outs)) != len(outs):
        raise ValueError(f"train_side_by_side: two seeds share a run folder: {runs}")
    for o in outs:
        o.mkdir(parents=True, exist_ok=True)
    mean_loss, _, validate_all = _objective(loss_fn, data, val, batch_loss, runs=len(runs))
    keys = [seed_keys(seed) for seed in runs]
    results = run_many(mean_loss, [init_fn(k_init) for k_init, _ in keys], data, cfg,
                       optimizer(cfg.lr, cfg.steps), [k_loop for _, k_loop in keys], outs=outs, log=log,
                       validate_all=validate_all)
    log(_time_split(results[0]) + f" ({len(runs)} runs side by side)")
    for o, res in zip(outs, results, strict=True):
        _write_summary(o, res, cfg)
    return {seed: res.params for seed, res in zip(runs, results, strict=True)}


def seed_keys(seed: int) -> tuple[jax.Array, jax.Array]:
    """``(init, loop)``: a run's initialisation key and its minibatch draws' key, from its seed
    (one derivation for a run alone and side by side)."""
    key_init, key_loop = jax.random.split(jax.random.key(seed))
    return key_init, key_loop


def _objective(loss_fn: Callable, data: dict, val: dict, batch_loss: Callable | None, runs: int = 1):
    """``(mean_loss, validate, validate_all)`` of :func:`train_examples`: a minibatch's mean loss
    and parts, the validation score and metrics of a parameter set, and the same for ``runs``
    parameter sets stacked (``loop.ValidateAll``: one vmapped program, each run's chunk of
    examples ``VALIDATION_CHUNK // runs`` so that a batched factorisation keeps its size)."""
    if len(data["q"]) == 0 or len(val["q"]) == 0:
        raise TrainingError("no valid training or validation steps in the dataset")

    def mean_loss(params, ex, key, chunk: int | None = None):
        """The examples' mean loss and parts, all at once (a training minibatch, through
        ``batch_loss`` where given) or ``chunk`` examples at a time (validation,
        ``VALIDATION_CHUNK``: a model's batched factorisations,
        a Cholesky per example and substep for the structured models, stay the minibatch's
        size; at 4096 at once jaxlib's batched LAPACK call hung on a 2-core CPU, DeLaN + MLP
        with the transition loss, measured twice)."""
        keys = jax.random.split(key, len(ex["q"]))
        if chunk is None and batch_loss is not None:
            return batch_loss(params, ex, keys)
        if chunk is None:
            total, parts = jax.vmap(loss_fn, in_axes=(None, 0, 0))(params, ex, keys)
        else:
            total, parts = jax.lax.map(lambda a: loss_fn(params, *a), (ex, keys),
                                       batch_size=chunk)
        return jnp.mean(total), jax.tree.map(jnp.mean, parts)

    eval_fn = jax.jit(lambda params, ex, key: mean_loss(params, ex, key, VALIDATION_CHUNK))
    eval_all = jax.jit(jax.vmap(lambda params, ex, key: mean_loss(params, ex, key, max(1, VALIDATION_CHUNK // runs)),
                                in_axes=(0, None, None)))
    val_ex = jax.tree.map(lambda a: a[: min(len(a), 4096)], val)

    def scored(val_loss, parts):
        # The best checkpoint: the lowest validation "select" part where the loss names one
        # (structured models: acceleration error plus the allocation term, not a total
        # dominated by the generator's loss), else the lowest total.
        return float(parts.get("select", val_loss)), {
            "val_loss": float(val_loss), **{f"val_{k}": float(v) for k, v in parts.items()}}

    def validate(params):
        return scored(*eval_fn(params, val_ex, jax.random.key(0)))

    def validate_all(params):
        val_loss, parts = jax.device_get(eval_all(params, val_ex, jax.random.key(0)))
        done = [scored(val_loss[i], {k: v[i] for k, v in parts.items()}) for i in range(len(val_loss))]
        return np.array([score for score, _ in done]), [metrics for _, metrics in done]

    return mean_loss, validate, validate_all


def _time_split(res) -> str:
    """Where a training call's wall time went (``loop.Result.seconds``), as the log says it."""
    return "time: " + ", ".join(f"{part} {sec:.1f} s" for part, sec in res.seconds.items())


def _write_summary(out: pathlib.Path, res, cfg: LoopConfig) -> None:
    atomic_write_text(out / "summary.json", json.dumps(
        {"best_val": res.best_score, "best_step": res.best_step,
         "params_sha256": params_sha256(res.params),
         "steps": cfg.steps, "steps_done": res.steps_done,
         "finished": res.steps_done >= cfg.steps}, indent=1))
