"""PPO warm-start policies on our MJX environments, in resumable chunks.

The algorithm is Brax's PPO (``brax.training.agents.ppo``: its networks, loss, GAE, observation
normaliser and unroll), driven by a small jitted loop of our own instead of
``brax.training.agents.ppo.train``: that function (brax 0.14.2) calls ``jax.device_put_replicated``,
which jax 0.10 removed, and with a shim its ``pmap`` path took 4 minutes on 2 CPU cores for 80 env
steps (a recompilation per epoch). Owning the loop also makes resuming exact: the whole
:class:`TrainState` -- parameters, Adam moments, normaliser, key -- is checkpointed.

A run folder holds

* ``config.json`` -- the :class:`PPOConfig` and the environment config it was started with;
* ``checkpoint.msgpack`` -- the :class:`TrainState` (normaliser, policy, value, optimiser state,
  key), total env steps and chunk count, in one file written atomically (a killed chunk leaves the
  previous checkpoint intact);
* ``progress.jsonl`` -- one line per checkpoint (episode reward terms, losses, steps/s).

A chunk starts from the checkpoint, resets every world with a key derived from (seed, chunk), and
runs ``checkpoints`` jitted epochs of PPO updates, saving after each. It ends after
``chunk_steps`` env steps or, with ``minutes``, at the last checkpoint that leaves room for one
more before the deadline (compilation included), so a chunk fits a time-boxed job. Resuming from
disk continues exactly as the in-memory run would (tested).

The learner (its config :class:`PPOConfig`, networks, training state, one jitted epoch, the
policy of its parameters) is :mod:`stride_jax.control.ppo_learner`; this module runs it: named
presets, chunks and checkpoints.
``policy(obs, key) -> action`` of a run is :func:`load_policy`; a planner that holds
``(q, qd, command)`` builds the observation with the environment's ``observation_fn``.

The job that runs one chunk into a run folder (writing ``config.json`` and ``progress.jsonl``,
resuming when ``--out`` holds a checkpoint) is ``stride ppo`` (:mod:`stride_jax.jobs.ppo`):

    stride ppo --robot go1 --preset gpu --out runs/ppo_go1 --minutes 8
"""

from __future__ import annotations

import dataclasses
import json
import pathlib
import time
from typing import Any, Callable

import jax
import jax.numpy as jnp
from flax import serialization

from stride_jax.control import envs
from stride_jax.control.ppo_learner import (  # noqa: F401 (the learner's names, re-exported)
    PPOConfig,
    Trainer,
    TrainState,
    init_state,
    make_policy,
    make_trainer,
    network_factory,
)
from stride_jax.io import atomic_write


PRESETS = {
    # Seconds on a CPU (plus compilation): the machinery, not a walking policy.
    "tiny": PPOConfig(num_envs=4, episode_length=20, unroll_length=5, batch_size=4,
                      num_minibatches=2, num_updates_per_batch=1, chunk_steps=80, checkpoints=2,
                      total_steps=160, policy_width=16, policy_depth=2, value_width=16,
                      value_depth=2),
    # A CPU sanity run (minutes): the policy starts to track the forward command.
    "cpu": PPOConfig(num_envs=32, episode_length=200, unroll_length=10, batch_size=32,
                     num_minibatches=4, num_updates_per_batch=2, chunk_steps=200_000,
                     checkpoints=10, total_steps=1_000_000, policy_width=64, policy_depth=3,
                     value_width=64, value_depth=3),
    # One H100/H200: MuJoCo Playground's Go1 joystick settings.
    "gpu": PPOConfig(),
    "default": PPOConfig(),
}


def preset(name: str, **overrides) -> PPOConfig:
    if name not in PRESETS:
        raise ValueError(f"unknown PPO preset {name!r}; choose from {', '.join(PRESETS)}")
    return dataclasses.replace(PRESETS[name], **overrides)


# ---------------------------------------------------------------------------------------------
# Checkpoints and chunks.


@dataclasses.dataclass(frozen=True)
class RunState:
    """What a run folder's checkpoint holds."""

    train: TrainState
    env_steps: int
    chunks: int


def save(out: pathlib.Path, state: RunState) -> None:
    blob = serialization.msgpack_serialize({
        "train": serialization.to_state_dict(jax.device_get(state.train)),
        "env_steps": state.env_steps, "chunks": state.chunks})
    atomic_write(pathlib.Path(out) / "checkpoint.msgpack", lambda f: f.write(blob))


def load(out: pathlib.Path, cfg: PPOConfig, obs_size: int, action_size: int) -> RunState | None:
    """The run's checkpoint, or None if it has none."""
    path = pathlib.Path(out) / "checkpoint.msgpack"
    if not path.is_file():
        return None
    raw = serialization.msgpack_restore(path.read_bytes())
    target = init_state(cfg, obs_size, action_size, jax.random.key(0))
    try:
        train = serialization.from_state_dict(target, raw["train"])
    except (KeyError, ValueError) as e:
        raise ValueError(f"{path} does not match the networks of {out}/config.json: {e}") from e
    shapes = lambda t: jax.tree.map(jnp.shape, t)
    if shapes(train) != shapes(target):
        raise ValueError(f"{path}: parameter shapes differ from the configured networks")
    train = jax.tree.map(lambda a, t: jnp.asarray(a, t.dtype), train, target)
    return RunState(train, int(raw["env_steps"]), int(raw["chunks"]))


def train_chunk(cfg: PPOConfig, env: Any, restore: RunState | None = None,
                on_checkpoint: Callable[[RunState, dict], None] | None = None,
                deadline: float | None = None, trainer: Trainer | None = None) -> RunState:
    """One chunk of PPO on ``env`` (an unwrapped Brax env), from ``restore`` if given.

    ``on_checkpoint(state, metrics)`` is called after every epoch; with ``deadline`` (a
    ``time.monotonic()`` value) the chunk ends at the last epoch that leaves time for one more.
    Returns the state at the end of the chunk (``restore`` itself when the run is complete).
    """
    trainer = trainer or make_trainer(cfg, env)
    if restore is None:
        restore = RunState(trainer.init(jax.random.key(cfg.seed)), 0, 0)
    per_epoch = trainer.updates_per_epoch * cfg.steps_per_update
    budget = min(cfg.chunk_steps, cfg.total_steps - restore.env_steps)
    n_epochs = -(-budget // per_epoch) if budget > 0 else 0
    if n_epochs == 0:
        return restore
    ts, steps, chunk = restore.train, restore.env_steps, restore.chunks + 1
    env_state = trainer.reset(jax.random.fold_in(jax.random.key(cfg.seed), chunk))
    state = restore
    for _ in range(n_epochs):
        t = time.monotonic()
        ts, env_state, metrics = trainer.epoch(ts, env_state)
        metrics = {k: float(v) for k, v in jax.device_get(metrics).items()}
        steps += per_epoch
        epoch_s = time.monotonic() - t
        metrics.update(sps=per_epoch / epoch_s, epoch_s=epoch_s)
        state = RunState(ts, steps, chunk)
        if on_checkpoint:
            on_checkpoint(state, metrics)
        if deadline is not None and time.monotonic() + 1.2 * epoch_s > deadline:
            break
    return state


# ---------------------------------------------------------------------------------------------
# Using a trained policy.


def read_config(out: str | pathlib.Path) -> tuple[PPOConfig, envs.EnvConfig]:
    path = pathlib.Path(out) / "config.json"
    if not path.is_file():
        raise FileNotFoundError(f"{out} is not a PPO run (no config.json); train one with "
                                "`stride ppo --out ...`")
    d = json.loads(path.read_text())
    e = d["env"]
    env_cfg = envs.EnvConfig(**{**e, "commands": envs.Commands(**{
        k: tuple(v) if isinstance(v, list) else v for k, v in e["commands"].items()}),
        "rewards": envs.RewardScales(**e["rewards"])})
    return PPOConfig(**d["ppo"]), env_cfg


def load_policy(out: str | pathlib.Path, deterministic: bool = True
                ) -> tuple[Callable[[jax.Array, jax.Array], jax.Array], Callable, envs.EnvConfig]:
    """``(policy(obs, key) -> action [nu] in [-1, 1], value(obs) -> [], env_config)`` of a run:
    plain jittable functions over closed-over parameters (the PPO critic is the value)."""
    cfg, env_cfg = read_config(out)
    from stride_jax.sim import model as sim_model
    nu = sim_model.load(env_cfg.robot).info.nu
    n_obs = envs.obs_size(env_cfg, nu)
    state = load(pathlib.Path(out), cfg, n_obs, nu)
    if state is None:
        raise FileNotFoundError(f"{out} holds no checkpoint yet")
    return make_policy(cfg, state.train.params, n_obs, nu, deterministic) + (env_cfg,)
