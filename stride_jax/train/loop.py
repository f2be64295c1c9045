"""The one training loop: optax steps on random minibatches, run as jitted ``lax.scan`` chunks,
with validation and best-parameter selection, resumable orbax checkpoints, a NaN guard, progress
and a CSV log.

Two layers, both used by every model trained with optax here (the dynamics models through
:mod:`stride_jax.train.dynamics`, the gap tool's STRIDE residual, the learned reward and value;
PPO keeps Brax's own loop):

* :func:`scan_steps` -- ``n`` optimiser steps as one ``lax.scan``: pure, jit-able, usable inside
  another ``scan`` (the value model's fitted-value-iteration rounds).
* :func:`run` -- the host loop around it: chunks of steps between validations and checkpoints,
  the best validated parameters, resumption from ``out/ckpt``, ``out/metrics.csv``, a progress
  bar.

Minibatch ``i`` is drawn with ``fold_in(key, i)``, so a run that was killed and resumed from its
last checkpoint takes exactly the steps an uninterrupted run takes, and the chunking does not
change the draws.
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import functools
import pathlib
import shutil
import time
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
import orbax.checkpoint as ocp
from jax.sharding import NamedSharding, PartitionSpec
from tqdm import tqdm

from stride_jax import distributed
from stride_jax.sim import rollout_mjx

# ``loss_fn(params, batch, key) -> (loss [], parts {name: []})``: the mean loss of a minibatch
# (every leaf of the data with a leading axis of ``batch``) and named parts to log.
LossFn = Callable[[Any, Any, jax.Array], tuple[jax.Array, dict]]


class TrainingError(RuntimeError):
    """Training cannot go on (a non-finite loss, an unusable checkpoint)."""


@dataclasses.dataclass(frozen=True)
class LoopConfig:
    """Optimisation: Adam with cosine decay from ``lr`` over ``steps`` minibatches of ``batch``
    examples; validation every ``eval_every`` steps, a checkpoint every ``ckpt_every``.

    Attributes:
      steps: optimiser steps.
      batch: examples per minibatch.
      lr: peak learning rate (cosine decay to 0.05 lr over ``steps``).
      eval_every: validate (and keep the best parameters) every this many steps.
      ckpt_every: write a checkpoint to resume from every this many steps.
      seed: minibatch draws and initialisation.
      deadline: Unix time (0 for none): stop cleanly at the first validation after it, with a
        checkpoint to resume from (for machines lent by the hour).
      stop_at: stop cleanly after this many steps (0: at ``steps``), validated and with a
        checkpoint to resume from, while the learning-rate schedule still spans ``steps``: a run
        trained in chunks, or one trained to the step where another run of the same schedule
        stopped (equal training, not a shorter schedule).
    """

    steps: int = 2000
    batch: int = 256
    lr: float = 1e-3
    eval_every: int = 100
    ckpt_every: int = 500
    seed: int = 0
    deadline: float = 0.0
    stop_at: int = 0

    def __post_init__(self):
        for name, least, need in (("steps", 1, "a positive integer"),
                                  ("batch", 1, "a positive integer"),
                                  ("eval_every", 1, "a positive integer"),
                                  ("ckpt_every", 1, "a positive integer"),
                                  ("stop_at", 0, "a step count >= 0 (0: none)")):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < least:
                raise ValueError(f"loop.{name}={v!r}: need {need}")
        if not (np.isfinite(self.lr) and self.lr > 0):
            raise ValueError(f"loop.lr={self.lr!r}: need a positive, finite learning rate")
        if not (np.isfinite(self.deadline) and self.deadline >= 0):
            raise ValueError(f"loop.deadline={self.deadline!r}: need a Unix time (0: none)")


def _end(cfg: LoopConfig) -> int:
    """The step a call of :func:`run` trains to: ``steps``, or ``stop_at`` before it."""
    return min(cfg.steps, cfg.stop_at) if cfg.stop_at > 0 else cfg.steps


def optimizer(lr: float, steps: int, weight_decay: float = 0.0) -> optax.GradientTransformation:
    """The house optimiser: gradients clipped at global norm 10, then Adam (AdamW with decoupled
    ``weight_decay`` > 0) with a cosine decay from ``lr`` to ``0.05 lr`` over ``steps``. (Plain
    Adam at 0: AdamW's extra state would not restore older checkpoints.)"""
    schedule = optax.cosine_decay_schedule(lr, steps, alpha=0.05)
    adam = optax.adamw(schedule, weight_decay=weight_decay) if weight_decay else \
        optax.adam(schedule)
    return optax.chain(optax.clip_by_global_norm(10.0), adam)


def scan_steps(loss_fn: LossFn, opt: optax.GradientTransformation, params: Any, opt_state: Any,
               data: Any, key: jax.Array, start: jax.Array | int, n: int, batch: int,
               sharding: Any = None) -> tuple[tuple[Any, Any], jax.Array, dict]:
    """Steps ``start .. start + n - 1`` of the optimiser as one ``lax.scan`` (pure; jit it).

    Step ``i`` takes ``k_batch, k_loss = split(fold_in(key, i))``, a minibatch of ``batch``
    examples drawn uniformly with replacement from ``data`` (a pytree of arrays ``[N, ...]``)
    with ``k_batch``, and one ``opt`` update on the gradient of ``loss_fn(params, minibatch,
    k_loss)``. ``sharding``: splits the minibatch over devices (XLA all-reduces the gradients).

    Returns ``((params, opt_state), losses [n], parts {name: [n]})``.
    """
    n_data = jax.tree.leaves(data)[0].shape[0]

    def step(carry, i):
        params, opt_state = carry
        k_batch, k_loss = jax.random.split(jax.random.fold_in(key, i))
        idx = jax.random.randint(k_batch, (batch,), 0, n_data)
        ex = jax.tree.map(lambda a: a[idx], data)
        if sharding is not None:
            ex = jax.lax.with_sharding_constraint(ex, sharding)
        (loss, parts), grads = jax.value_and_grad(loss_fn, has_aux=True)(params, ex, k_loss)
        updates, opt_state = opt.update(grads, opt_state, params)
        return (optax.apply_updates(params, updates), opt_state), (loss, parts)

    carry, (losses, parts) = jax.lax.scan(step, (params, opt_state), start + jnp.arange(n))
    return carry, losses, parts


class Result(NamedTuple):
    """What :func:`run` returns.

    Attributes:
      params: the best validated parameters (the last without a ``validate``).
      losses: ``[steps run by this call]`` the training loss of every step.
      checked_at: the steps validated by this call.
      scores: their validation scores (lower is better).
      best_step: the step of ``params``.
      best_score: its validation score (inf without a ``validate``).
      steps_done: the steps taken, counting those of a resumed run.
      seconds: wall time of this call by part (``train``: the optimiser's chunks, their
        compilation included; ``validate``; ``save``: checkpoints handed to orbax and waited for;
        ``other``: the rest, from the first chunk's start to returning).
    """

    params: Any
    losses: np.ndarray
    checked_at: list[int]
    scores: list[float]
    best_step: int
    best_score: float
    steps_done: int
    seconds: dict | None = None


def _manager(path: pathlib.Path, max_to_keep: int) -> ocp.CheckpointManager:
    """A checkpoint manager with the unfinished steps of a killed run removed.

    A process killed while saving can leave a step folder that orbax does not count as a
    checkpoint (no commit marker) but that blocks saving that step again after resuming.
    """
    path = path.absolute()
    # Several processes: orbax's async saves name their cross-process barrier after the step
    # alone, so the latest and the best checkpoint of one step (two managers) collided
    # ("Barrier _async_write_complete.30 is already ongoing"); save synchronously there.
    options = ocp.CheckpointManagerOptions(max_to_keep=max_to_keep, create=True,
                                           cleanup_tmp_directories=True,
                                           enable_async_checkpointing=jax.process_count() == 1)
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


def _next_stop(step: int, cfg: LoopConfig, validating: bool, saving: bool) -> int:
    """Where the chunk that starts after ``step`` ends: the next validation, the next
    checkpoint or the last step of this call (``stop_at``)."""
    stop = _end(cfg)
    if validating:
        stop = min(stop, (step // cfg.eval_every + 1) * cfg.eval_every)
    if saving:
        stop = min(stop, (step // cfg.ckpt_every + 1) * cfg.ckpt_every)
    return stop


class _Clock:
    """Wall seconds by part of a training call (:attr:`Result.seconds`): ``with clock(part):``;
    :meth:`split` adds ``other``, the rest of the time since the clock started (the loop's own
    host work: metrics rows, the progress bar, copies between devices)."""

    def __init__(self):
        self.start = time.perf_counter()
        self.seconds = {"train": 0.0, "validate": 0.0, "save": 0.0}

    def split(self) -> dict[str, float]:
        return {**self.seconds, "other": time.perf_counter() - self.start - sum(self.seconds.values())}

    @contextlib.contextmanager
    def __call__(self, part: str):
        t = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[part] += time.perf_counter() - t


class _Log:
    """Rows of ``metrics.csv``, appended (the file is opened per row: one per validation); a
    resumed run keeps the columns of the file's header."""

    def __init__(self, path: pathlib.Path | None):
        self.path, self.fields = path, None
        if path is not None and path.exists():
            header = path.read_text().split("\n", 1)[0]
            self.fields = next(csv.reader([header]), None) if header else None

    def write(self, row: dict) -> None:
        if self.path is None:
            return
        new = self.fields is None
        self.fields = self.fields or list(row)
        with open(self.path, "a", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=self.fields, extrasaction="ignore")
            if new:
                writer.writeheader()
            writer.writerow(row)


def _marks(step: int, end: int, cfg: LoopConfig) -> tuple[bool, bool, bool]:
    """``(last, held, validate)`` at the end of a chunk: the schedule's last step, a stop by
    ``stop_at`` (validated and saved), and whether validation runs here."""
    last, held = step == cfg.steps, step == end < cfg.steps
    return last, held, step % cfg.eval_every == 0 or last or held


def _after(step: int, cfg: LoopConfig, last: bool, held: bool) -> tuple[bool, str]:
    """``(save, stop)`` after a chunk's validation: whether a checkpoint is written here, and
    why the loop stops before the schedule's end (empty: it goes on), as the log says it."""
    out_of_time = bool(cfg.deadline) and step % cfg.eval_every == 0 and time.time() > cfg.deadline
    save = step % cfg.ckpt_every == 0 or last or out_of_time or held
    if held:
        return save, (f"stopped at step {step} of {cfg.steps} (stop_at); run again with a later "
                      "stop_at (or none) to go on")
    if out_of_time and not last:
        return save, f"deadline reached: stopped at step {step} of {cfg.steps}; run again to resume"
    return save, ""


def _diverged(losses: np.ndarray, step: int, cfg: LoopConfig, last_good: tuple | None,
              who: str = "") -> TrainingError:
    """The error for a chunk whose ``losses`` are not all finite; ``last_good``: (checkpoint
    folder, its latest step) or None without checkpoints; ``who``: which run, where several."""
    bad = losses[~np.isfinite(losses)][0]
    where = f"; the last good checkpoint is in {last_good[0]} (step {last_good[1]})" if last_good else ""
    return TrainingError(f"{who}the training loss became {bad} by step {step}{where}. Lower the "
                         f"learning rate ({cfg.lr}) or check the data for outliers.")


def run(loss_fn: LossFn, params: Any, data: Any, cfg: LoopConfig,
        opt: optax.GradientTransformation, key: jax.Array,
        validate: Callable[[Any], tuple[float, dict[str, float]]] | None = None,
        out: pathlib.Path | None = None, log: Callable[[str], None] = print,
        progress: str | None = "train") -> Result:
    """Trains ``params`` on ``loss_fn`` (see :data:`LossFn`) over ``data`` (a pytree of arrays
    ``[N, ...]``) for ``cfg.steps`` minibatches of ``min(cfg.batch, N)`` with ``opt``.

    ``validate(params) -> (score, metrics)`` runs every ``cfg.eval_every`` steps and after the
    last; the parameters with the lowest score are returned. ``out``: a run folder; then
    ``out/ckpt`` holds the latest state (every ``cfg.ckpt_every`` steps; a later call resumes
    from it), ``out/best`` the best validated parameters up to it (written with each checkpoint,
    not at every validation, which cost time on a GPU: a run resumed from a checkpoint finds any
    later best again) and ``out/metrics.csv`` one row per
    validation (step, time, training loss and parts, ``metrics``). Without ``out`` nothing is
    written and the best parameters are kept in memory. ``progress``: the progress bar's label
    (None: no bar). Raises :class:`TrainingError` when the loss stops being finite.
    """
    n_data = jax.tree.leaves(data)[0].shape[0]
    batch = min(cfg.batch, n_data)
    state = {"params": params, "opt": opt.init(params), "step": jnp.zeros((), jnp.int32),
             "best_val": jnp.array(jnp.inf, jnp.float32)}
    ckpt = best = None
    if out is not None:
        out = pathlib.Path(out)
        ckpt, best = _manager(out / "ckpt", 2), _manager(out / "best", 1)
        if ckpt.latest_step() is not None:
            try:
                state = ckpt.restore(ckpt.latest_step(), args=ocp.args.StandardRestore(state))
            except Exception as e:  # noqa: BLE001 -- any unreadable checkpoint is the same problem
                raise TrainingError(f"cannot resume from {out / 'ckpt'}: {e}") from e
            log(f"resumed from step {int(state['step'])} ({out / 'ckpt'})")
        # Best checkpoints saved after the resumed step belong to the lost part of a killed run.
        for s in best.all_steps():
            if s > int(state["step"]):
                best.delete(s)

    # Several processes (stride_jax.distributed): one mesh over every device of every process,
    # data, parameters and optimiser state replicated on it, each minibatch split over it.
    multi = jax.process_count() > 1
    if multi:
        on = distributed.mesh()
        if batch % jax.device_count():
            raise TrainingError(f"batch {batch} does not split over the job's "
                                f"{jax.device_count()} devices; use a multiple of it")
        sharding = NamedSharding(on, PartitionSpec("batch"))
        data, state = distributed.replicate(data, on), distributed.replicate(state, on)
        key_data = distributed.replicate(jax.random.key_data(key), on)
    else:
        sharding = rollout_mjx.world_sharding(batch) \
            if batch % max(1, jax.local_device_count()) == 0 else None
        if sharding is None:
            data = jax.device_put(data)  # the training set lives on the device once
        else:  # several local devices: data, parameters and optimiser state replicated on each,
            # so every device gathers its own half of the minibatch and only the gradients
            # travel (data left on the first device made each step on 2 H100s 4x slower than on
            # one, 223 against 882 steps/s: half the examples/s; results/scale/)
            rep = NamedSharding(sharding.mesh, PartitionSpec())
            data, state = jax.device_put(data, rep), jax.device_put(state, rep)
        key_data = jax.random.key_data(key)
    if multi:
        host = distributed.to_host
    elif sharding is not None:  # validation and checkpoints on one device: a checkpoint that
        # restores anywhere, and no replicated validation (which hangs on forced CPU devices)
        host = functools.partial(jax.device_put, device=jax.local_devices()[0])
    else:
        host = lambda tree: tree  # noqa: E731
    main = distributed.is_main()

    # The data and the key are arguments, not constants of the program: no dataset baked into
    # the executable, and runs that differ only in their seed share the compilation cache.
    @functools.partial(jax.jit, static_argnames="n")
    def chunk(params, opt_state, data, key_data, start, n):
        return scan_steps(loss_fn, opt, params, opt_state, data,
                          jax.random.wrap_key_data(key_data), start, n, batch, sharding)

    step = start = int(state["step"])
    kept, best_step, best_score = state["params"], step, float(state["best_val"])
    unsaved = False  # a best found since the last checkpoint, written with the next one
    losses, checked_at, scores = [], [], []
    clock = _Clock()
    metrics_log = _Log(out / "metrics.csv" if out is not None and main else None)
    with tqdm(total=cfg.steps, initial=start, desc=progress, unit="step",
              disable=progress is None or not main) as bar:
        end = _end(cfg)
        while step < end:
            stop = _next_stop(step, cfg, validate is not None, ckpt is not None)
            with clock("train"):
                (p, o), chunk_losses, parts = chunk(state["params"], state["opt"], data, key_data,
                                                    step, n=stop - step)
                chunk_losses, parts = jax.device_get((chunk_losses, parts))  # waits for the chunk
            state = dict(state, params=p, opt=o, step=jnp.asarray(stop, jnp.int32))
            bar.update(stop - step)
            step = stop
            losses.append(chunk_losses)
            if not np.isfinite(chunk_losses).all():
                raise _diverged(chunk_losses, step, cfg,
                                (out / "ckpt", ckpt.latest_step()) if ckpt is not None else None)
            last, held, validating = _marks(step, end, cfg)
            if validate is not None and validating:
                with clock("validate"):
                    score, metrics = validate(host(state["params"]))
                checked_at.append(step)
                scores.append(float(score))
                metrics_log.write({"step": step, "time": time.time(),
                                   "train_loss": float(chunk_losses[-1]),
                                   **{f"train_{k}": float(v[-1]) for k, v in parts.items()},
                                   **metrics})
                if score < best_score:
                    state = dict(state, best_val=jnp.asarray(score, jnp.float32))
                    kept, best_step, best_score = state["params"], step, float(score)
                    unsaved = best is not None
                bar.set_postfix(loss=f"{float(chunk_losses[-1]):.4g}", val=f"{score:.4g}")
            elif validate is None:
                kept, best_step = state["params"], step
            save, stop = _after(step, cfg, last, held)
            if ckpt is not None and save:
                with clock("save"):
                    if unsaved:
                        best.save(best_step, args=ocp.args.StandardSave(host(kept)), force=True)
                        unsaved = False
                    ckpt.save(step, args=ocp.args.StandardSave(host(state)), force=True)
            if stop:
                log(stop)
                break
    if ckpt is not None:
        with clock("save"):
            ckpt.wait_until_finished()
            best.wait_until_finished()
        if validate is not None:
            if best.latest_step() is None:
                raise TrainingError("no validation ever ran (steps < eval_every?)")
            best_step = best.latest_step()
            kept = best.restore(best_step,
                                args=ocp.args.StandardRestore(host(state["params"])))
    return Result(host(kept), np.concatenate(losses) if losses else np.zeros(0), checked_at, scores,
                  best_step, best_score, step, clock.split())


def _stack(trees: list) -> Any:
    return jax.tree.map(lambda *a: jnp.stack(a), *trees)


def _take(tree: Any, i: int) -> Any:
    return jax.tree.map(lambda a: a[i], tree)


def _restore_together(ckpts: list[ocp.CheckpointManager], states: list[dict], outs: list[pathlib.Path],
                      log: Callable[[str], None]) -> list[dict]:
    """Each run's latest checkpoint, at one step for all: a run killed between the runs' saves can
    leave them a save apart, and the side-by-side program needs one step; the latest step that
    every run holds (each keeps its last two) is restored."""
    if all(c.latest_step() is None for c in ckpts):
        return states
    common = set.intersection(*(set(c.all_steps()) for c in ckpts))
    if not common:
        have = {str(o / "ckpt"): c.latest_step() for o, c in zip(outs, ckpts, strict=True)}
        raise TrainingError(f"cannot resume the runs side by side: their checkpoints share no step "
                            f"({have}); train them one by one to a common step, or remove the checkpoints")
    step = max(common)
    for c in ckpts:  # a later save of one run: redone with the others (saving a step twice fails)
        for s in c.all_steps():
            if s > step:
                c.delete(s)
    try:
        states = [c.restore(step, args=ocp.args.StandardRestore(s)) for c, s in zip(ckpts, states, strict=True)]
    except Exception as e:  # noqa: BLE001 -- any unreadable checkpoint is the same problem
        raise TrainingError(f"cannot resume from {[str(o / 'ckpt') for o in outs]} at step {step}: {e}") from e
    log(f"resumed {len(ckpts)} runs from step {step}")
    return states


# ``validate_all(params) -> (scores [runs], [metrics {name: float}] per run)``: every run's
# validation at once, the runs' parameters stacked on a leading axis (:func:`run_many`).
ValidateAll = Callable[[Any], tuple[np.ndarray, list[dict[str, float]]]]


def one_by_one(validate: Callable[[Any], tuple[float, dict[str, float]]]) -> ValidateAll:
    """A single run's ``validate(params) -> (score, metrics)`` as :data:`ValidateAll`: each run's
    parameters taken from the stack and validated in turn."""
    def validate_all(params):
        n = jax.tree.leaves(params)[0].shape[0]
        done = [validate(_take(params, i)) for i in range(n)]
        return np.array([float(score) for score, _ in done]), [metrics for _, metrics in done]
    return validate_all


def run_many(loss_fn: LossFn, params: list, data: Any, cfg: LoopConfig,
             opt: optax.GradientTransformation, keys: list[jax.Array],
             validate: Callable[[Any], tuple[float, dict[str, float]]] | None = None,
             outs: list[pathlib.Path] | None = None, log: Callable[[str], None] = print,
             progress: str | None = "train", validate_all: ValidateAll | None = None) -> list[Result]:
    """:func:`run` for several independent runs side by side in one program: the same loss, data
    and schedule, each run its own initial ``params[i]`` and ``keys[i]`` (its minibatch draws), the
    optimiser steps of all vmapped over the runs.

    Why: at the paper's size and batch a training step is a sequence of a few hundred kernels of a
    few microseconds each, the GPU mostly idle between them (``results/throughput/README.md``);
    three runs side by side take 1.4x one run's time on Go1, eight 2.4x. On a CPU, whose cores the
    one run already fills, it gains nothing.

    Each run is what :func:`run` makes of its ``params[i]`` and ``keys[i]`` (the same start and
    draws; the batched products round differently, which long training amplifies: on a GPU the
    runs' final losses differed from the single runs' within the seeds' own spread after 6000
    steps, ``results/throughput/README.md``): its own folder ``outs[i]`` with
    ``ckpt`` (the run's own state, which a single :func:`run` into that folder also resumes),
    ``best`` (its best validated parameters) and ``metrics.csv``, and its own best step. One
    process; several local devices each take an equal share of the runs (all on the first where
    the runs do not split evenly).

    ``validate`` validates one run's parameters as :func:`run`'s does, the runs in turn;
    ``validate_all`` (:data:`ValidateAll`, instead of it) all runs at once from their stacked
    parameters, which keeps the side-by-side gain through validation (one vmapped program
    instead of a program per run: ``train.dynamics.train_side_by_side``).
    """
    n = len(params)
    if n < 1 or len(keys) != n or (outs is not None and len(outs) != n):
        raise ValueError(f"run_many: {n} parameter sets, {len(keys)} keys and "
                         f"{'no' if outs is None else len(outs)} folders: need one of each per run")
    if jax.process_count() > 1:
        raise TrainingError("runs side by side train on one process; train them one by one over several processes")
    if validate is not None and validate_all is not None:
        raise ValueError("run_many: give validate (one run at a time) or validate_all (all at once), not both")
    n_data = jax.tree.leaves(data)[0].shape[0]
    batch = min(cfg.batch, n_data)
    states = [{"params": p, "opt": opt.init(p), "step": jnp.zeros((), jnp.int32),
               "best_val": jnp.array(jnp.inf, jnp.float32)} for p in params]
    ckpts = bests = None
    if outs is not None:
        outs = [pathlib.Path(o) for o in outs]
        ckpts = [_manager(o / "ckpt", 2) for o in outs]
        bests = [_manager(o / "best", 1) for o in outs]
        states = _restore_together(ckpts, states, outs, log)
        for b in bests:  # best checkpoints after the resumed step belong to the lost part of a run
            for s in b.all_steps():
                if s > int(states[0]["step"]):
                    b.delete(s)
    # Several local devices: the runs split over them (each device its share of the runs, the
    # data replicated; no traffic between them), where they split evenly; else all on the first.
    devices = jax.local_devices()
    first = devices[0]
    if len(devices) > 1 and n % len(devices) == 0:
        mesh = jax.sharding.Mesh(np.array(devices), ("runs",))
        on_runs, everywhere = NamedSharding(mesh, PartitionSpec("runs")), NamedSharding(mesh, PartitionSpec())
        log(f"{n} runs side by side over {len(devices)} devices, {n // len(devices)} each")
    else:
        if len(devices) > 1:
            log(f"{n} runs do not split evenly over {len(devices)} devices: all train on the first")
        on_runs = everywhere = first
    data = jax.device_put(data, everywhere)
    state = jax.device_put(_stack(states), on_runs)
    key_data = jax.device_put(jnp.stack([jax.random.key_data(k) for k in keys]), on_runs)
    # one run's share, on the first device, for its validation and its files
    one = lambda tree, i: jax.device_put(_take(tree, i), first)  # noqa: E731
    if validate is not None:  # the runs in turn, each on the first device as run() validates
        validate_all = one_by_one(lambda p: validate(jax.device_put(p, first)))

    @functools.partial(jax.jit, static_argnames="n")
    def chunk(params, opt_state, data, key_data, start, n):
        each = lambda p, o, kd: scan_steps(loss_fn, opt, p, o, data, jax.random.wrap_key_data(kd), start, n, batch)
        return jax.vmap(each)(params, opt_state, key_data)

    step = start = int(state["step"][0])
    kept = [one(state["params"], i) for i in range(n)]
    best_step = [step] * n
    best_score = [float(s) for s in state["best_val"]]
    unsaved = [False] * n  # as in run: each run's best written with its next checkpoint
    losses, checked_at, scores = [], [], [[] for _ in range(n)]
    clock = _Clock()
    logs = [_Log(o / "metrics.csv" if o is not None else None) for o in (outs or [None] * n)]
    with tqdm(total=cfg.steps, initial=start, desc=f"{progress} x{n}" if progress else None, unit="step",
              disable=progress is None) as bar:
        end = _end(cfg)
        while step < end:
            stop = _next_stop(step, cfg, validate_all is not None, ckpts is not None)
            with clock("train"):
                (p, o), chunk_losses, parts = chunk(state["params"], state["opt"], data, key_data, step,
                                                    n=stop - step)
                # [runs, steps]; waits for the chunk; the parts in the same copy (one per part
                # and run, each its own wait, when read one by one)
                chunk_losses, parts = jax.device_get((chunk_losses, parts))
            state = dict(state, params=p, opt=o, step=jnp.full((n,), stop, jnp.int32))
            bar.update(stop - step)
            step = stop
            losses.append(chunk_losses)
            if not np.isfinite(chunk_losses).all():
                i = int(np.nonzero(~np.isfinite(chunk_losses).all(1))[0][0])
                raise _diverged(chunk_losses[i], step, cfg,
                                (outs[i] / "ckpt", ckpts[i].latest_step()) if ckpts is not None else None,
                                f"run {i} of {n}: ")
            last, held, validating = _marks(step, end, cfg)
            if validate_all is not None and validating:
                checked_at.append(step)
                best_val = np.array(state["best_val"])
                with clock("validate"):
                    all_scores, all_metrics = validate_all(state["params"])
                if len(all_scores) != n or len(all_metrics) != n:
                    raise ValueError(f"run_many: validate_all returned {len(all_scores)} scores and "
                                     f"{len(all_metrics)} metrics for {n} runs")
                for i, (score, metrics) in enumerate(zip(all_scores, all_metrics)):
                    scores[i].append(float(score))
                    logs[i].write({"step": step, "time": time.time(),
                                   "train_loss": float(chunk_losses[i, -1]),
                                   **{f"train_{k}": float(v[i, -1]) for k, v in parts.items()}, **metrics})
                    if score < best_score[i]:
                        best_val[i] = score
                        kept[i], best_step[i], best_score[i] = one(state["params"], i), step, float(score)
                        unsaved[i] = bests is not None
                state = dict(state, best_val=jnp.asarray(best_val, jnp.float32))
                bar.set_postfix(loss=f"{float(chunk_losses[:, -1].mean()):.4g}",
                                val=f"{np.mean([s[-1] for s in scores]):.4g}")
            elif validate_all is None:
                kept = [one(state["params"], i) for i in range(n)]
                best_step = [step] * n
            save, stop = _after(step, cfg, last, held)
            if ckpts is not None and save:
                with clock("save"):
                    for i, c in enumerate(ckpts):
                        if unsaved[i]:
                            bests[i].save(best_step[i], args=ocp.args.StandardSave(kept[i]), force=True)
                            unsaved[i] = False
                        c.save(step, args=ocp.args.StandardSave(one(state, i)), force=True)
            if stop:
                log(stop)
                break
    if ckpts is not None:
        with clock("save"):
            for c, b in zip(ckpts, bests, strict=True):
                c.wait_until_finished()
                b.wait_until_finished()
        if validate_all is not None:
            for i, b in enumerate(bests):
                if b.latest_step() is None:
                    raise TrainingError("no validation ever ran (steps < eval_every?)")
                best_step[i] = b.latest_step()
                kept[i] = b.restore(best_step[i], args=ocp.args.StandardRestore(kept[i]))
    run_losses = np.concatenate(losses, 1) if losses else np.zeros((n, 0))
    split = clock.split()
    return [Result(kept[i], run_losses[i], checked_at, scores[i], best_step[i], best_score[i], step,
                   dict(split)) for i in range(n)]
