"""The training loop: jitted optax steps on minibatches sharded over devices, validation,
best-checkpoint selection, resumable orbax checkpoints, a NaN guard, progress and a CSV log.

Minibatch ``i`` is drawn with ``fold_in(key, i)``, so a run that was killed and resumed from its
last checkpoint takes exactly the steps an uninterrupted run takes.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import pathlib
import shutil
import time
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
import optax
import orbax.checkpoint as ocp
from tqdm import tqdm

from stride_jax.dynamics.checkpoint import params_sha256
from stride_jax.sim import rollout_mjx
from stride_jax.io import atomic_write_text


class TrainingError(RuntimeError):
    """Training cannot go on (a non-finite loss, an unusable checkpoint)."""


@dataclasses.dataclass(frozen=True)
class LoopConfig:
    """Optimisation: Adam with cosine decay from ``lr`` over ``steps`` minibatches of ``batch``
    examples; validation every ``eval_every`` steps, a checkpoint every ``ckpt_every``.
    ``deadline`` (Unix time, 0 for none): stop cleanly at the first validation after it, with a
    checkpoint to resume from (for machines lent by the hour)."""

    steps: int = 2000
    batch: int = 256
    lr: float = 1e-3
    eval_every: int = 100
    ckpt_every: int = 500
    seed: int = 0
    deadline: float = 0.0


def _examples(split: dict, jacobians: Callable | None = None) -> dict:
    """Transitions between consecutive valid steps as flat examples [N, ...]: the step's
    ``q, qd, tau, qdd, ctrl``, the next step's ``q_next, qd_next``, and ``contact_jac``
    ``[N, nfeet * k, nv]``, the sole Jacobians of the feet in contact (zero rows for feet in
    swing; training-time supervision only, see ``stride.loss``).

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
    ex = {k: np.asarray(a, np.float32) for k, a in ex.items()}
    bad = {k: int((~np.isfinite(a.reshape(len(a), -1))).any(-1).sum()) for k, a in ex.items()}
    if any(bad.values()):
        raise TrainingError(f"non-finite values in valid dataset steps ({bad}); regenerate the "
                            "dataset with this version, which marks such steps invalid")
    return ex


def _manager(path: pathlib.Path, max_to_keep: int) -> ocp.CheckpointManager:
    """A checkpoint manager with the unfinished steps of a killed run removed.

    A process killed while saving can leave a step folder that orbax does not count as a
    checkpoint (no commit marker) but that blocks saving that step again after resuming.
    """
    path = path.absolute()
    options = ocp.CheckpointManagerOptions(max_to_keep=max_to_keep, create=True,
                                           cleanup_tmp_directories=True)
    mngr = ocp.CheckpointManager(path, options=options)
    mngr.reload()
    finished = set(mngr.all_steps())
    stale = [p for p in path.iterdir() if p.name.isdigit() and int(p.name) not in finished]
    if not stale:
        return mngr
    mngr.close()
    for p in stale:
        shutil.rmtree(p)
    return ocp.CheckpointManager(path, options=options)


def train(loss_fn: Callable, init_fn: Callable, train_split: dict, val_split: dict,
          cfg: LoopConfig, out: pathlib.Path, log: Callable[[str], None] = print,
          jacobians: Callable | None = None) -> dict:
    """Trains ``init_fn(key)`` params on ``loss_fn(params, example, key)``; returns the best params.

    Writes ``out/ckpt`` (latest, resumable), ``out/best`` (lowest validation ``select`` part of
    the loss where it has one, else the lowest validation loss) and
    ``out/metrics.csv``; resumes from ``out/ckpt`` when it exists. ``jacobians``: see
    ``_examples``.
    """
    data, val = _examples(train_split, jacobians), _examples(val_split, jacobians)
    return train_examples(loss_fn, init_fn, data, val, cfg, out, log)


def train_examples(loss_fn: Callable, init_fn: Callable, data: dict, val: dict,
                   cfg: LoopConfig, out: pathlib.Path, log: Callable[[str], None] = print
                   ) -> dict:
    """:func:`train` on flat examples ``{name: [N, ...]}`` (``q, qd, tau, qdd``, and whatever
    else ``loss_fn`` reads) for training and validation. ``out/summary.json`` records the best
    step and the SHA-256 of its parameters (``checkpoint.params_sha256``)."""
    out = pathlib.Path(out)
    out.mkdir(parents=True, exist_ok=True)
    n_train = len(data["q"])
    if n_train == 0 or len(val["q"]) == 0:
        raise TrainingError("no valid training or validation steps in the dataset")
    key = jax.random.key(cfg.seed)
    key_init, key_loop = jax.random.split(key)
    schedule = optax.cosine_decay_schedule(cfg.lr, cfg.steps, alpha=0.05)
    opt = optax.chain(optax.clip_by_global_norm(10.0), optax.adam(schedule))
    params = init_fn(key_init)
    state = {"params": params, "opt": opt.init(params), "step": jnp.zeros((), jnp.int32),
             "best_val": jnp.array(jnp.inf, jnp.float32)}

    ckpt, best = _manager(out / "ckpt", 2), _manager(out / "best", 1)
    if ckpt.latest_step() is not None:
        try:
            state = ckpt.restore(ckpt.latest_step(), args=ocp.args.StandardRestore(state))
        except Exception as e:  # noqa: BLE001 -- any unreadable checkpoint is the same problem
            raise TrainingError(f"cannot resume from {out / 'ckpt'}: {e}") from e
        log(f"resumed from step {int(state['step'])} ({out / 'ckpt'})")
    # Best checkpoints saved after the resumed step belong to the lost part of a killed run.
    for step in best.all_steps():
        if step > int(state["step"]):
            best.delete(step)

    batch = min(cfg.batch, n_train)
    sharding = rollout_mjx.world_sharding(batch) if batch % max(1, jax.local_device_count()) == 0 \
        else None
    # The training set lives on the device(s) once; minibatches are gathered there.
    data = jax.device_put(data)

    def mean_loss(params, ex, key):
        keys = jax.random.split(key, len(ex["q"]))
        total, parts = jax.vmap(loss_fn, in_axes=(None, 0, 0))(params, ex, keys)
        return jnp.mean(total), jax.tree.map(jnp.mean, parts)

    # The key is an argument, not a constant of the program: runs that differ only in their seed
    # compile to the same program and share JAX's persistent compilation cache.
    @jax.jit
    def train_step(state, data, key_loop, i):
        k_batch, k_loss = jax.random.split(jax.random.fold_in(key_loop, i))
        idx = jax.random.randint(k_batch, (batch,), 0, n_train)
        ex = {k: v[idx] for k, v in data.items()}
        if sharding is not None:  # split the minibatch over devices; XLA all-reduces the grads
            ex = jax.lax.with_sharding_constraint(ex, sharding)
        (loss, parts), grads = jax.value_and_grad(mean_loss, has_aux=True)(state["params"], ex,
                                                                           k_loss)
        updates, opt_state = opt.update(grads, state["opt"], state["params"])
        new = dict(state, params=optax.apply_updates(state["params"], updates), opt=opt_state,
                   step=state["step"] + 1)
        return new, loss, parts

    eval_fn = jax.jit(mean_loss)
    val_ex = jax.tree.map(lambda a: a[: min(len(a), 4096)], val)
    metrics_path = out / "metrics.csv"
    new_file = not metrics_path.exists()
    start = int(state["step"])
    with open(metrics_path, "a", newline="") as f, tqdm(total=cfg.steps, initial=start,
                                                        desc="train", unit="step") as bar:
        writer = None
        for i in range(start, cfg.steps):
            state, loss, parts = train_step(state, data, key_loop, i)
            step = i + 1
            last = step == cfg.steps
            if step % cfg.eval_every == 0 or last:
                loss = float(loss)
                if not np.isfinite(loss):
                    raise TrainingError(
                        f"the training loss became {loss} by step {step}; the last good "
                        f"checkpoint is in {out / 'ckpt'} (step {ckpt.latest_step()}). Lower "
                        f"the learning rate ({cfg.lr}) or check the dataset for outliers.")
                val_loss, val_parts = eval_fn(state["params"], val_ex, jax.random.key(0))
                row = {"step": step, "time": time.time(), "train_loss": loss,
                       "val_loss": float(val_loss),
                       **{f"train_{k}": float(v) for k, v in parts.items()},
                       **{f"val_{k}": float(v) for k, v in val_parts.items()}}
                if writer is None:
                    writer = csv.DictWriter(f, fieldnames=list(row))
                    if new_file:
                        writer.writeheader()
                writer.writerow(row)
                f.flush()
                # The best checkpoint: the lowest validation "select" part where the loss names
                # one (structured models: acceleration error plus the allocation term, not a
                # total dominated by the generator's loss), else the lowest total.
                val_select = float(val_parts.get("select", val_loss))
                if val_select < float(state["best_val"]):
                    state = dict(state, best_val=jnp.asarray(val_select, jnp.float32))
                    best.save(step, args=ocp.args.StandardSave(state["params"]), force=True)
                bar.set_postfix(loss=f"{loss:.4g}", val=f"{float(val_loss):.4g}")
            out_of_time = bool(cfg.deadline) and step % cfg.eval_every == 0 and \
                time.time() > cfg.deadline
            if step % cfg.ckpt_every == 0 or last or out_of_time:
                ckpt.save(step, args=ocp.args.StandardSave(state), force=True)
            bar.update(1)
            if out_of_time and not last:
                log(f"deadline reached: stopped at step {step} of {cfg.steps}; run again to "
                    "resume")
                break
    ckpt.wait_until_finished()
    best.wait_until_finished()
    if best.latest_step() is None:
        raise TrainingError("no validation ever ran (steps < eval_every?)")
    params = best.restore(best.latest_step(), args=ocp.args.StandardRestore(state["params"]))
    atomic_write_text(out / "summary.json", json.dumps(
        {"best_val": float(state["best_val"]), "best_step": best.latest_step(),
         "params_sha256": params_sha256(params),
         "steps": cfg.steps, "steps_done": int(state["step"]),
         "finished": int(state["step"]) >= cfg.steps}, indent=1))
    return params
