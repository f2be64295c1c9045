"""Brax training wrappers for the velocity-command environments (:mod:`stride_jax.control.envs`):
vmap, episode counting, and resets of finished worlds to a fresh draw of start and command."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from brax.envs import base as brax_base
from brax.envs.wrappers import training as brax_wrappers


# Info keys of Brax's episode bookkeeping, which survive a reset (the rest is the env's own).
BOOKKEEPING = ("steps", "truncation", "episode_done", "episode_metrics", "reset_rng", "last_obs")


class FreshResetWrapper(brax_base.Wrapper):
    """Resets finished worlds to a new draw of ``reset`` (new start, new command), keeping the
    episode bookkeeping of :class:`brax.envs.wrappers.training.EpisodeWrapper` as Brax's own
    ``AutoResetWrapper`` does. Wraps a batched environment. ``info['last_obs']`` keeps the
    observation a step reached before a reset replaced it (for value targets)."""

    def reset(self, rng: jax.Array) -> brax_base.State:
        state = self.env.reset(rng)
        state.info["reset_rng"] = jax.vmap(lambda k: jax.random.fold_in(k, 1))(rng)
        state.info["last_obs"] = state.obs
        return state

    def step(self, state: brax_base.State, action: jax.Array) -> brax_base.State:
        if "steps" in state.info:
            state.info["steps"] = jnp.where(state.done, 0.0, state.info["steps"])
        state = state.replace(done=jnp.zeros_like(state.done))
        state = self.env.step(state, action)
        keys = jax.vmap(jax.random.split)(state.info["reset_rng"])
        fresh = self.env.reset(keys[:, 1])
        done = state.done

        def pick(new, old):
            return jnp.where(done.reshape(done.shape + (1,) * (old.ndim - 1)), new, old)

        info = dict(state.info)
        for k in fresh.info:
            if k not in BOOKKEEPING:
                info[k] = jax.tree.map(pick, fresh.info[k], state.info[k])
        info["reset_rng"] = keys[:, 0]
        info["last_obs"] = state.obs
        return state.replace(pipeline_state=jax.tree.map(pick, fresh.pipeline_state,
                                                         state.pipeline_state),
                             obs=pick(fresh.obs, state.obs), info=info)


def wrap_for_training(env: brax_base.Env, episode_length: int = 1000, action_repeat: int = 1,
                      randomization_fn: Any = None) -> brax_base.Wrapper:
    """Vmap, episode counting and fresh resets; the ``wrap_env_fn`` of ``ppo.train``."""
    if randomization_fn is not None:
        raise NotImplementedError("domain randomisation is not wired into these environments")
    env = brax_wrappers.VmapWrapper(env)
    env = brax_wrappers.EpisodeWrapper(env, episode_length, action_repeat)
    return FreshResetWrapper(env)
