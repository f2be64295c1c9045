"""Conditional flow matching (the paper's Sec. III-C): a context-conditioned vector field, its loss,
and a sampler with a chosen number of function evaluations (NFE).

With the straight (rectified) probability path ``z_t = (1 - t) z0 + t x1``, ``z0 ~ N(0, I)``, the
field ``v(z_t, t | c)`` regresses the constant velocity ``x1 - z0`` (Lipman et al., 2023). A
sample is ``z0 + integral_0^1 v(z_t, t | c) dt``, integrated with ``nfe`` evaluations: Euler
takes ``nfe`` steps, midpoint ``nfe / 2`` steps of two evaluations each. Written for one example;
``vmap`` over a batch.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from stride_jax.dynamics import fused, mlp
from stride_jax.dynamics.time_embedding import time_embedding

INTEGRATORS = ("euler", "midpoint")


@dataclasses.dataclass(frozen=True)
class FlowConfig:
    """Vector-field size, time embedding and the sampler's budget."""

    net: mlp.MLPConfig = mlp.MLPConfig()
    time_features: int = 8  # sinusoidal features of t
    nfe: int = 2
    integrator: str = "euler"
    kernel: str = "xla"  # sampling: XLA's ops or a fused kernel (fused.KERNELS; Euler only)

    def __post_init__(self):
        if self.integrator not in INTEGRATORS:
            raise ValueError(f"integrator {self.integrator!r} is not one of {INTEGRATORS}")
        if fused.kernel_dtype(self.kernel) is not None and self.integrator != "euler":
            raise ValueError(f"kernel {self.kernel!r} samples with Euler steps only, "
                             f"not {self.integrator!r}")
        if self.nfe < 1 or (self.integrator == "midpoint" and self.nfe % 2):
            raise ValueError(f"nfe={self.nfe}: need >= 1 (and even for midpoint)")


def flow_init(key: jax.Array, dim: int, context_dim: int, cfg: FlowConfig = FlowConfig()) -> dict:
    """Parameters of ``v(z [dim], t | c [context_dim])``; the field starts at zero."""
    init, _ = mlp.mlp(cfg.net, dim, zero_last=True)
    return init(key, dim + cfg.time_features + context_dim)


def vector_field(params: dict, z: jax.Array, t: jax.Array, context: jax.Array,
                 cfg: FlowConfig = FlowConfig()) -> jax.Array:
    """``v(z, t | c)`` ``[dim]``."""
    _, apply = mlp.mlp(cfg.net, z.shape[-1], zero_last=True)
    return apply(params, jnp.concatenate([z, time_embedding(t, cfg.time_features), context]))


def fm_loss(params: dict, x1: jax.Array, context: jax.Array, key: jax.Array,
            cfg: FlowConfig = FlowConfig()) -> jax.Array:
    """Conditional flow-matching loss of one example: ``|v(z_t, t | c) - (x1 - z0)|^2``."""
    key_t, key_z = jax.random.split(key)
    t = jax.random.uniform(key_t)
    z0 = jax.random.normal(key_z, x1.shape, x1.dtype)
    zt = (1.0 - t) * z0 + t * x1
    return jnp.sum((vector_field(params, zt, t, context, cfg) - (x1 - z0)) ** 2)


def integrate(params: dict, z0: jax.Array, context: jax.Array, cfg: FlowConfig = FlowConfig(),
              nfe: int | None = None) -> jax.Array:
    """Transports ``z0`` to a sample: ``z0 + integral_0^1 v dt`` with ``nfe`` evaluations
    (with a fused ``cfg.kernel``: one kernel for the whole sample, under ``vmap`` on GPUs)."""
    nfe = nfe or cfg.nfe
    dtype = fused.kernel_dtype(cfg.kernel)
    if dtype is not None:
        return fused.flow_euler(params, z0, context, nfe, cfg.time_features, dtype)
    field = lambda z, t: vector_field(params, z, t, context, cfg)
    if cfg.integrator == "euler":
        dt = 1.0 / nfe
        step = lambda z, i: (z + dt * field(z, i * dt), None)
    else:
        if nfe % 2:
            raise ValueError(f"midpoint needs an even nfe, got {nfe}")
        dt = 2.0 / nfe
        step = lambda z, i: (z + dt * field(z + 0.5 * dt * field(z, i * dt), (i + 0.5) * dt), None)
    n_steps = nfe if cfg.integrator == "euler" else nfe // 2
    # Up to 4 steps per loop iteration: sampling budgets are 1-4 steps, which then compile to
    # straight-line code that XLA can schedule (and put in one CUDA graph) as a whole.
    z, _ = jax.lax.scan(step, z0, jnp.arange(n_steps, dtype=z0.dtype), unroll=min(n_steps, 4))
    return z


def sample(params: dict, context: jax.Array, key: jax.Array, dim: int,
           cfg: FlowConfig = FlowConfig(), nfe: int | None = None) -> jax.Array:
    """One sample ``[dim]`` of the conditional distribution given ``context``."""
    return integrate(params, jax.random.normal(key, (dim,)), context, cfg, nfe)


def central(params: dict, context: jax.Array, dim: int, cfg: FlowConfig = FlowConfig(),
            nfe: int | None = None) -> jax.Array:
    """The transport of ``z0 = 0``, the latent's centre ``[dim]``: a deterministic summary of
    the distribution (its mean for a Gaussian, a point between the modes of a symmetric mixture)."""
    return integrate(params, jnp.zeros((dim,)), context, cfg, nfe)
