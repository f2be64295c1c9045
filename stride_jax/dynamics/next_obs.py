"""Next-observation baselines: ONN (an MLP) and Pure Diffusion (a DDPM), no physics inside.

Both model the one-control-step change ``x = (difference(q', q) / sigma_dq, (qd' - qd) / sigma_dqd)``
given the context ``(features(q), qd / sigma_qd, ctrl / sigma_ctrl)``. ONN regresses it with the
squared error (the paper's "RMSE between predicted and ground-truth next observations"); Pure
Diffusion learns its conditional distribution with the denoising loss and samples it with
``nfe`` evaluations.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from stride_jax.dynamics import integrate, lagrangian, mlp
from stride_jax.dynamics.stride import Scales, StructuredConfig, dof_weights, gravity_features
from stride_jax.types import ModelSpec


def _context(spec: ModelSpec, q, qd, ctrl, scales: Scales, down=None, gravity: bool = False):
    """``(features(q), qd, ctrl)`` normalised; ``gravity`` (``gravity_context``): and gravity's
    direction in the base's frame (:func:`stride.gravity_features` of ``down``)."""
    parts = [lagrangian.q_features(spec, q), qd / scales.qd, ctrl / scales.ctrl]
    if gravity:
        parts.append(gravity_features(spec, q, down))
    return jnp.concatenate(parts)


def _target(spec: ModelSpec, scales: Scales, ex: dict) -> jax.Array:
    return jnp.concatenate([
        integrate.difference(ex["q_next"], ex["q"], spec.floating_base) / scales.dq,
        (ex["qd_next"] - ex["qd"]) / scales.dqd])


def init(key: jax.Array, spec: ModelSpec, cfg: StructuredConfig, nu: int, scales: Scales,
         generative_kind: str | None = None) -> dict:
    """Parameters of the regressor (``generative_kind=None``) or of the generator."""
    q0 = jnp.zeros(spec.nq).at[3].set(1.0) if spec.floating_base else jnp.zeros(spec.nq)
    n_in = _context(spec, q0, jnp.zeros(spec.nv), jnp.zeros(nu), scales,
                    gravity=cfg.gravity_context).shape[0]
    if generative_kind is None:
        return mlp.mlp(cfg.net, 2 * spec.nv, zero_last=True)[0](key, n_in)
    return cfg.generator(generative_kind).init(key, 2 * spec.nv, n_in)


def step(params: dict, spec: ModelSpec, cfg: StructuredConfig, scales: Scales, q, qd, ctrl,
         key=None, nfe: int | None = None, generative_kind: str | None = None, down=None):
    """Next ``(q', qd')`` after one control period under ``ctrl`` (a generator's sample;
    ``key=None``: its central sample); ``down``: gravity's direction, seen with
    ``cfg.gravity_context``."""
    c = _context(spec, q, qd, ctrl, scales, down, cfg.gravity_context)
    if generative_kind is None:
        out = mlp.mlp(cfg.inference_net, 2 * spec.nv, zero_last=True)[1](params, c)
    elif key is None:
        out = cfg.generator(generative_kind).central(params, c, 2 * spec.nv, nfe)
    else:
        out = cfg.generator(generative_kind).sample(params, c, key, 2 * spec.nv, nfe)
    dq, dqd = out[:spec.nv] * scales.dq, out[spec.nv:] * scales.dqd
    return integrate.retract(q, dq, spec.floating_base), qd + dqd


def loss(params: dict, spec: ModelSpec, cfg: StructuredConfig, scales: Scales, ex: dict,
         key=None, generative_kind: str | None = None):
    cfg = dataclasses.replace(cfg, kernel="xla")  # training differentiates in float32 XLA
    c = _context(spec, ex["q"], ex["qd"], ex["ctrl"], scales, ex.get("down"),
                 cfg.gravity_context)
    target = _target(spec, scales, ex)
    if generative_kind is None:
        out = mlp.mlp(cfg.net, 2 * spec.nv, zero_last=True)[1](params, c)
        w = dof_weights(spec, cfg)  # the base's pose change and velocity rows, the joints' 1
        l_obs = jnp.sum(jnp.concatenate([w, w]) * (out - target) ** 2)
        return l_obs, {"obs": l_obs}
    l_gen = cfg.generator(generative_kind).loss(params, target, c, key)
    return l_gen, {"ddpm" if generative_kind == "diffusion" else "fm": l_gen}
