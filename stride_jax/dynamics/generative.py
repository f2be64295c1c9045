"""Conditional samplers ``x ~ p(x | c)`` behind one shape, so the models swap them freely.

``flow`` is conditional flow matching (STRIDE's residual), ``diffusion`` is DDPM (the diffusion
baselines). Both take ``nfe`` network evaluations per sample; the evaluation and the inference
benchmark vary it at sampling time.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, NamedTuple

import jax

from stride_jax.dynamics import diffusion, flow, mlp

KINDS = ("flow", "diffusion")


class Generator(NamedTuple):
    """A conditional sampler as pure functions; meets :class:`stride_jax.types.Generator`."""

    init: Callable  # (key, dim, context_dim) -> params
    loss: Callable  # (params, x [dim], context, key) -> scalar training loss of one example
    sample: Callable  # (params, context, key, dim, nfe=None) -> x [dim]
    central: Callable  # (params, context, dim, nfe=None) -> x [dim]: the latent's centre mapped
    mean: Callable | None = None  # (params, context, dim) -> x [dim]: a deterministic part,
    # trained by the caller (with_mean); None: the generator has none


def with_mean(gen: Generator, net: mlp.MLPConfig) -> Generator:
    """``x = m(c) + y``: a mean head ``m``, an MLP of size ``net``, plus ``gen`` for the remainder
    ``y``. ``gen`` is trained by its own loss on ``x - m(c)`` with ``m`` held fixed there, so it
    models the spread around ``m``; ``m`` gets no gradient from that loss: the caller trains it
    (STRIDE's acceleration loss, ``acc_through="mean"``). Parameters ``{'mean', 'gen'}``."""
    head = lambda dim: mlp.mlp(net, dim, zero_last=True)

    def init(key, dim, cdim):
        key_mean, key_gen = jax.random.split(key)
        return {"mean": head(dim)[0](key_mean, cdim), "gen": gen.init(key_gen, dim, cdim)}

    def mean(p, c, dim):
        return head(dim)[1](p["mean"], c)

    def loss(p, x, c, key):
        return gen.loss(p["gen"], x - jax.lax.stop_gradient(mean(p, c, x.shape[-1])), c, key)

    return Generator(init, loss,
                     lambda p, c, key, dim, nfe=None: mean(p, c, dim) + gen.sample(
                         p["gen"], c, key, dim, nfe),
                     lambda p, c, dim, nfe=None: mean(p, c, dim) + gen.central(
                         p["gen"], c, dim, nfe),
                     mean)


def make(kind: str, net: mlp.MLPConfig, nfe: int, integrator: str = "euler",
         kernel: str = "xla", diffusion_cfg: diffusion.DiffusionConfig | None = None
         ) -> Generator:
    """``kernel``: how the flow samples (``fused.KERNELS``); diffusion always samples in XLA,
    with ``diffusion_cfg``'s schedule and parameterisation (its ``net`` and ``nfe`` are
    replaced by these arguments)."""
    if kind == "flow":
        cfg = flow.FlowConfig(net=net, nfe=nfe, integrator=integrator, kernel=kernel)
        return Generator(lambda key, dim, cdim: flow.flow_init(key, dim, cdim, cfg),
                         lambda p, x, c, key: flow.fm_loss(p, x, c, key, cfg),
                         lambda p, c, key, dim, nfe=None: flow.sample(p, c, key, dim, cfg, nfe),
                         lambda p, c, dim, nfe=None: flow.central(p, c, dim, cfg, nfe))
    if kind == "diffusion":
        cfg = dataclasses.replace(diffusion_cfg or diffusion.DiffusionConfig(), net=net, nfe=nfe)
        return Generator(lambda key, dim, cdim: diffusion.init(key, dim, cdim, cfg),
                         lambda p, x, c, key: diffusion.loss(p, x, c, key, cfg),
                         lambda p, c, key, dim, nfe=None: diffusion.sample(p, c, key, dim, cfg,
                                                                           nfe),
                         lambda p, c, dim, nfe=None: diffusion.sample(
                             p, c, jax.random.key(0), dim, cfg, nfe, central=True))
    raise ValueError(f"unknown generator {kind!r}; available: {', '.join(KINDS)}")
