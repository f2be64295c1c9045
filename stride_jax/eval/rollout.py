"""Open-loop H-step rollout error in observation space (the paper's Table I "state RMSE").

From the start of each window of ``H + 1`` valid steps of held-out episodes, a model rolls out the
logged commands for ``H`` control steps. At horizon ``h`` the error is the RMSE over all
observation dimensions of

    [ difference(q_pred, q_true) / sigma_dq ,  (qd_pred - qd_true) / sigma_qd ]

where ``difference`` is the tangent-space difference (world position, body-frame rotation vector,
joint angles), ``sigma_qd`` the per-dof standard deviation of the velocities and ``sigma_dq`` that
of the one-step configuration change times ``H`` -- so that both halves are O(1) across the
horizon. The cumulative error is the sum over ``h = 1..H`` of the per-horizon RMSE, averaged over
windows; stochastic models report its mean and spread over samples.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from stride_jax.dynamics import integrate
from stride_jax.sim import record
from stride_jax.types import ModelSpec


def windows(valid: np.ndarray, horizon: int, max_windows: int, seed: int = 0) -> np.ndarray:
    """``[N, 2]`` (episode, start) pairs whose ``horizon + 1`` steps are all valid."""
    starts = np.zeros((0, 2), np.int64)
    if valid.shape[1] > horizon:
        ok = np.lib.stride_tricks.sliding_window_view(valid, horizon + 1, axis=1).all(-1)
        starts = np.argwhere(ok)
    if len(starts) == 0:
        raise ValueError(f"no window of {horizon + 1} valid steps in the evaluation data")
    rng = np.random.default_rng(seed)
    return starts[rng.permutation(len(starts))[:max_windows]]


def observation_scales(split: dict, spec: ModelSpec, horizon: int) -> tuple[np.ndarray, np.ndarray]:
    """``(sigma_dq [nv], sigma_qd [nv])`` from a split (see the module docstring)."""
    dq, _ = integrate.one_step_changes(split, spec.floating_base)
    floor = lambda s: np.maximum(s, 1e-3 * max(float(s.max()), 1e-6))
    return floor(dq.std(0) * horizon), floor(split["qd"][split["valid"]].std(0))


def normalised_errors(q, qd, q_ref, qd_ref, scales, floating_base: bool) -> jax.Array:
    """``[H, 2 nv]``: the error of ``(q [H, nq], qd [H, nv])`` against a reference trajectory in
    the normalised observation coordinates of the module docstring (jittable)."""
    sig_dq, sig_qd = (jnp.asarray(x) for x in scales)
    dq = jax.vmap(lambda a, b: integrate.difference(a, b, floating_base))(q, q_ref)
    return jnp.concatenate([dq / sig_dq, (qd - qd_ref) / sig_qd], axis=-1)


def rollout_error_vectors(rollout_fn, params, split: dict, spec: ModelSpec, horizon: int,
                          starts: np.ndarray, scales: tuple[np.ndarray, np.ndarray],
                          keys: jax.Array) -> np.ndarray:
    """``[S, N, H, 2 nv]``: normalised errors (module docstring) of ``rollout_fn(params, q, qd,
    ctrls, key)`` from ``N`` windows against the logged futures, one independent sample per key
    of ``keys [S]``, all in one compiled call. The parameters and windows are arguments of the
    compiled program, not constants in it, so runs of one model (seeds) share a compilation
    (and JAX's persistent cache). On sloped data (:func:`window_down` not ``None``) each
    window's gravity direction is passed too: ``rollout_fn(..., key, down=[3])``."""
    q, qd, ctrl = window_arrays(split, starts, horizon)
    down = window_down(split, starts)
    fb = spec.floating_base

    def per_key(params, q, qd, ctrl, down, scales, keys):
        def one(q, qd, ctrl, d, k):
            told = {} if d is None else {"down": d}
            q_pred, qd_pred = rollout_fn(params, q[0], qd[0], ctrl, k, **told)
            return normalised_errors(q_pred, qd_pred, q[1:], qd[1:], scales, fb)

        return jax.vmap(lambda k: jax.vmap(one)(q, qd, ctrl, down,
                                                jax.random.split(k, len(q))))(keys)

    scales = tuple(jnp.asarray(x) for x in scales)
    return np.asarray(jax.jit(per_key)(params, q, qd, ctrl, down, scales, keys))


def window_down(split: dict, starts: np.ndarray) -> jax.Array | None:
    """``[N, 3]``: gravity's direction at each window's start on sloped data (constant over an
    episode), ``None`` on level data (:func:`stride_jax.sim.record.down_of`)."""
    down = record.down_of(split)
    return None if down is None else jnp.asarray(down[starts[:, 0], starts[:, 1]])


def window_arrays(split: dict, starts: np.ndarray, horizon: int):
    """``(q [N, H+1, nq], qd [N, H+1, nv], ctrl [N, H, nu])`` of the windows ``starts``."""
    ep, t0 = starts[:, 0], starts[:, 1]
    idx = t0[:, None] + np.arange(horizon + 1)[None]
    q = jnp.asarray(split["q"][ep[:, None], idx], jnp.float32)
    qd = jnp.asarray(split["qd"][ep[:, None], idx], jnp.float32)
    ctrl = jnp.asarray(split["ctrl"][ep[:, None], idx[:, :-1]], jnp.float32)
    return q, qd, ctrl


def per_horizon_rmse(errors: np.ndarray) -> np.ndarray:
    """``[..., H]``: RMSE over the observation entries of normalised errors ``[..., H, D]``."""
    return np.sqrt(np.mean(errors ** 2, axis=-1))


def rollout_errors(rollout_fn, params, split: dict, spec: ModelSpec, horizon: int,
                   starts: np.ndarray, scales: tuple[np.ndarray, np.ndarray],
                   key: jax.Array) -> np.ndarray:
    """Per-window, per-horizon RMSE ``[N, H]`` of ``rollout_fn(params, q, qd, ctrls, key)``;
    ``key`` may also be ``S`` keys (stochastic models): then ``[S, N, H]``."""
    keys = key[None] if key.ndim == 0 else key
    errs = per_horizon_rmse(rollout_error_vectors(rollout_fn, params, split, spec, horizon,
                                                  starts, scales, keys))
    return errs[0] if key.ndim == 0 else errs


def cumulative_rmse(errors: np.ndarray) -> float:
    """Sum over the horizon of the per-horizon RMSE, averaged over windows."""
    return float(errors.sum(-1).mean())
