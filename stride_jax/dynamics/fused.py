"""Fused network passes for planners on GPUs: one Pallas (Triton) kernel per pass of an MLP.

A planner's model step on a GPU is bound by the number of kernels it launches, not by arithmetic
(``results/mppi_latency/README.md``: ~70 kernels of ~3.5 us per horizon step, 13x above the FLOP floor). XLA
runs each of an MLP's matrix products as its own kernel, and a tangent or a transposed pass as
more of them. Here every pass is one kernel over blocks of rows (samples):

* :func:`jvp` -- outputs and their derivative along one tangent (the Lagrangian networks'
  forward and tangent passes together);
* :func:`vjp` -- the input cotangent of an output cotangent (the forward pass recomputed in the
  kernel, then the transposed pass);
* :func:`flow_euler` -- a whole flow-matching sample: ``nfe`` Euler steps of the vector field.

Each is written for one example, like the rest of the library: called unbatched it is plain JAX;
under ``vmap`` (a planner's samples) it becomes one kernel for the whole batch
(``jax.custom_batching.custom_vmap``) on a GPU, and the same batched maths in plain JAX on a CPU.
They are inference-only: nothing here is differentiable (training keeps XLA's autodiff).

The kernels and their layout are in :mod:`stride_jax.dynamics.fused_pallas`; the
``pallas-step`` choices of :data:`KERNELS` go further and run a STRIDE model's whole step as one
kernel (:mod:`stride_jax.dynamics.fused_step`, 2.5 ms for the MPPI step below at 64 x 3).

Status (one H100, Go1, 1024 samples; commands and numbers in ``results/mppi_latency/README.md``): at the
paper's 256 x 3 a program streams ~0.7 MB of weights for only 16 rows, and the kernels are no
faster than XLA per pass (jvp 74 vs 47 us, vjp 64 vs 51 us, a flow sample 59 vs 60 us, 45 us
with bfloat16 products). At planning sizes they are: 64 x 3 per pass 18-24 us against XLA's
25-34, and a whole MPPI step (K = 1024, H = 30, STRIDE NFE 2) 6.09 ms in XLA, 5.41 ms fused,
5.12 ms fused with bfloat16 products. Select them with ``StructuredConfig.kernel``
(``bench-mppi --kernel``). A first version with the layers unrolled was 7x slower: ``ncu``
showed 32 registers and a 13.5 kB stack per thread, warps stalled on local memory (its weight
loads spilled), hence the tile loops.
"""

from __future__ import annotations

import functools
from typing import Callable

import jax
import jax.numpy as jnp

from stride_jax.dynamics.fused_pallas import (_INTERPRET, _silu, fits, flow_batched, interpret,
                                              jvp_batched, vjp_batched)
from stride_jax.dynamics.time_embedding import time_embedding

# --- the networks' parameters -----------------------------------------------------------------


def _layers(params: dict) -> list[tuple[jax.Array, jax.Array]]:
    """``[(W [din, dout], b [dout]), ...]`` of an :func:`mlp.mlp` network, input to output."""
    dense = params["params"]
    return [(dense[f"Dense_{i}"]["kernel"], dense[f"Dense_{i}"]["bias"])
            for i in range(len(dense))]


# --- reference maths (one example or a batch: rows are the last-but-one axis) -----------------


def _forward_ref(layers, x):
    for i, (w, b) in enumerate(layers):
        x = x @ w + b
        if i < len(layers) - 1:
            x = _silu(x)
    return x


def _jvp_ref(layers, x, t):
    return jax.jvp(lambda x: _forward_ref(layers, x), (x,), (t,))


def _vjp_ref(layers, x, g):
    return jax.vjp(lambda x: _forward_ref(layers, x), x)[1](g)[0]


def _flow_ref(layers, z, c, nfe, time_features):
    """``nfe`` Euler steps of ``v(z, t | c)`` (:func:`flow.integrate`'s Euler path)."""

    dt = 1.0 / nfe
    for i in range(nfe):
        emb = jnp.broadcast_to(time_embedding(i * dt, time_features),
                               z.shape[:-1] + (time_features,))
        z = z + dt * _forward_ref(layers, jnp.concatenate([z, emb, c], axis=-1))
    return z


# --- one example in, a batch under vmap -------------------------------------------------------


def _batched(kernel_fn: Callable, ref_fn: Callable, n_out: int,
             batched_ref: Callable | None = None) -> Callable:
    """``f(layers, *xs)`` for one example; under ``vmap`` (unbatched weights) one kernel for the
    batch on GPUs (``kernel_fn``), the batched reference on CPUs (``batched_ref``; by default
    ``ref_fn`` itself, for references written for any leading batch). Weights batched with the
    inputs (an ensemble) share no kernel: then ``ref_fn`` is vmapped. A network too wide for
    shared memory (:func:`fused_pallas.fits`) takes the batched reference everywhere."""
    @jax.custom_batching.custom_vmap
    def f(layers, *xs):
        return ref_fn(layers, *xs)

    @f.def_vmap
    def rule(axis_size, in_batched, layers, *xs):
        layers_batched, xs_batched = in_batched[0], in_batched[1:]
        out_batched = (True,) * n_out if n_out > 1 else True
        if any(jax.tree.leaves(layers_batched)):  # per-sample weights: no shared kernel
            axes = (jax.tree.map(lambda b: 0 if b else None, layers_batched),
                    *[0 if b else None for b in xs_batched])
            return jax.vmap(ref_fn, in_axes=axes)(layers, *xs), out_batched
        xs = [x if b else jnp.broadcast_to(x, (axis_size,) + x.shape)
              for x, b in zip(xs, xs_batched)]
        if not fits(layers):
            return (batched_ref or ref_fn)(layers, *xs), out_batched
        if _INTERPRET.get():
            return kernel_fn(layers, *xs), out_batched
        return jax.lax.platform_dependent(layers, *xs, cpu=batched_ref or ref_fn,
                                          default=kernel_fn), out_batched

    return f


def jvp(params: dict, x: jax.Array, t: jax.Array, dtype=jnp.float32
        ) -> tuple[jax.Array, jax.Array]:
    """``(f(x), df(x) t)`` of an :func:`mlp.mlp` network with ``params``; ``x, t [din]``.
    ``dtype``: the kernel's matrix-product inputs (float32 or bfloat16; accumulation float32)."""
    f = _batched(functools.partial(jvp_batched, dtype=dtype), _jvp_ref, 2)
    return f(_layers(params), x, t)


def vjp(params: dict, x: jax.Array, g: jax.Array, dtype=jnp.float32) -> jax.Array:
    """``df(x)^T g`` ``[din]`` of an :func:`mlp.mlp` network, ``g [dout]``."""
    f = _batched(functools.partial(vjp_batched, dtype=dtype), _vjp_ref, 1)
    return f(_layers(params), x, g)


def flow_euler(params: dict, z0: jax.Array, context: jax.Array, nfe: int,
               time_features: int, dtype=jnp.float32) -> jax.Array:
    """A flow-matching sample ``[dim]`` from ``z0 [dim]``: :func:`flow.integrate` with Euler
    steps, the vector field's ``params`` and its input ``(z, time embedding, context)``."""
    if nfe < 1:
        raise ValueError(f"flow_euler needs nfe >= 1, got {nfe}")
    f = _batched(lambda layers, z, c: flow_batched(layers, z, c, nfe, time_features, dtype),
                 lambda layers, z, c: _flow_ref(layers, z, c, nfe, time_features), 1)
    return f(_layers(params), z0, context)


# name -> the kernels' matrix-product type (None: XLA's own ops). The ``-step`` choices run a
# floating-base STRIDE model's whole step as one kernel (``fused_step``) where the model allows
# it (``models._whole_step_applies``); other models take the per-pass kernels. ``xla-bf16`` is
# XLA's own ops with every network's products in bfloat16 (``MLPConfig.products``): on a CPU
# with bfloat16 dot instructions the paper's 256 x 3 planner runs ~1.65x faster
# (``results/mppi_latency/README.md``).
KERNELS = {"xla": None, "xla-bf16": None, "pallas": jnp.float32, "pallas-bf16": jnp.bfloat16,
           "pallas-step": jnp.float32, "pallas-step-bf16": jnp.bfloat16}


def kernel_dtype(kernel: str):
    """The fused kernels' product type for a kernel choice (None: XLA's own ops)."""
    if kernel not in KERNELS:
        raise ValueError(f"unknown kernel {kernel!r}; available: {', '.join(KERNELS)}")
    return KERNELS[kernel]


def fused(kernel: str) -> bool:
    """Whether a kernel choice runs the networks as fused (Pallas) kernels."""
    return kernel_dtype(kernel) is not None


def products(kernel: str) -> str | None:
    """The networks' product type a kernel choice imposes on XLA's ops (``MLPConfig.products``):
    ``"bfloat16"`` for ``xla-bf16``, None (the network's own) otherwise."""
    kernel_dtype(kernel)
    return "bfloat16" if kernel == "xla-bf16" else None


def whole_step(kernel: str) -> bool:
    """Whether a kernel choice asks for the whole-step kernel (``fused_step``)."""
    kernel_dtype(kernel)
    return kernel.startswith("pallas-step")


__all__ = ["KERNELS", "flow_euler", "fused", "interpret", "jvp", "kernel_dtype", "products", "vjp",
           "whole_step"]
