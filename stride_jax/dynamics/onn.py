"""ONN: the unstructured baseline, an MLP from (observation, command) to the next observation.

It predicts the one-control-step change ``(difference(q', q) / sigma_dq, (qd' - qd) / sigma_dqd)``
from ``(features(q), qd / sigma_qd, ctrl / sigma_ctrl)``, trained with the squared error of that
normalised change (the paper's "RMSE between predicted and ground-truth next observations").
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from stride_jax.dynamics import integrate, lagrangian, mlp
from stride_jax.dynamics.stride import Scales
from stride_jax.types import ModelSpec


def _inputs(spec: ModelSpec, q, qd, ctrl, scales: Scales):
    return jnp.concatenate([lagrangian.q_features(spec, q), qd / scales.qd, ctrl / scales.ctrl])


def init(key: jax.Array, spec: ModelSpec, net: mlp.MLPConfig, nu: int, scales: Scales) -> dict:
    q0 = jnp.zeros(spec.nq).at[3].set(1.0) if spec.floating_base else jnp.zeros(spec.nq)
    n_in = _inputs(spec, q0, jnp.zeros(spec.nv), jnp.zeros(nu), scales).shape[0]
    return mlp.mlp(net, 2 * spec.nv, zero_last=True)[0](key, n_in)


def step(params: dict, spec: ModelSpec, net: mlp.MLPConfig, scales: Scales, q, qd, ctrl):
    """Next ``(q', qd')`` after one control period under ``ctrl``."""
    out = mlp.mlp(net, 2 * spec.nv, zero_last=True)[1](params, _inputs(spec, q, qd, ctrl, scales))
    dq, dqd = out[:spec.nv] * scales.dq, out[spec.nv:] * scales.dqd
    return integrate.retract(q, dq, spec.floating_base), qd + dqd


def loss(params: dict, spec: ModelSpec, net: mlp.MLPConfig, scales: Scales, ex: dict):
    out = mlp.mlp(net, 2 * spec.nv, zero_last=True)[1](
        params, _inputs(spec, ex["q"], ex["qd"], ex["ctrl"], scales))
    target = jnp.concatenate([
        integrate.difference(ex["q_next"], ex["q"], spec.floating_base) / scales.dq,
        (ex["qd_next"] - ex["qd"]) / scales.dqd])
    l_obs = jnp.sum((out - target) ** 2)
    return l_obs, {"obs": l_obs}
