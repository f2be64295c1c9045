"""The sinusoidal time embedding of the flow's vector field, shared by the XLA path
(:mod:`stride_jax.dynamics.flow`) and the fused kernels (:mod:`stride_jax.dynamics.fused`,
``fused_pallas``, ``fused_step``), which must embed ``t`` exactly as the field was trained."""

from __future__ import annotations

import jax
import jax.numpy as jnp


def time_embedding(t: jax.Array, n: int) -> jax.Array:
    """``[n]`` features of a scalar time ``t`` in [0, 1]: ``sin`` then ``cos`` of
    ``pi 2^k t`` for ``k < n / 2``."""
    freqs = jnp.pi * 2.0 ** jnp.arange(n // 2)
    return jnp.concatenate([jnp.sin(freqs * t), jnp.cos(freqs * t)])
