"""Denoising diffusion: the generative baselines' conditional sampler (LNN + Diffusion, Pure
Diffusion).

Training noises a target ``x0`` to ``x_s = sqrt(abar_s) x0 + sqrt(1 - abar_s) e`` at a random
level ``s`` of a ``steps``-level cosine schedule (Nichol & Dhariwal, 2021) and regresses a
context-conditioned network's output onto its ``target``:

* ``"v"`` (the default): ``v = sqrt(abar) e - sqrt(1 - abar) x0`` (Salimans & Ho, 2022);
* ``"x0"``: the clean sample itself;
* ``"eps"``: the noise ``e`` (DDPM, Ho et al. 2020; the parameterisation of runs made before v).

All three give the denoiser's clean-sample estimate ``x0_hat(x_s, s | c)``. Sampling starts from
``x ~ N(0, I)`` and denoises along ``nfe`` evenly spaced levels with the DDIM update (Song et al.,
2021): ``eta = 0`` (the default) is the deterministic DDIM map, ``eta = 1`` ancestral sampling on
the respaced schedule. Each level costs one network evaluation.

Why v and a schedule that ends at ``abar_T = abar_min`` (1e-3), both measured: with noise
prediction the clean estimate is ``(x - sqrt(1 - abar) e_hat) / sqrt(abar)``, so a network error
``d`` in ``e_hat`` becomes ``d / sqrt(abar)`` in ``x0_hat``. The first version's cosine schedule,
clipped at ``abar_T = 1e-5``, magnified it ~316x at the noisiest level: at NFE 1, 91.5% of a
trained Go1 residual's entries hit the +-10 clip and rollouts reached 1e13. With v,
``x0_hat = sqrt(abar) x - sqrt(1 - abar) v_hat``, an error ``d`` stays ``<= d`` at every level
(``tests/test_diffusion.py`` checks the one-step error on a known Gaussian). The clean estimate is
clipped to ``+-clip`` (targets are normalised: a few sigma). Written for one example; ``vmap``
over a batch.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import jax
import jax.numpy as jnp

from stride_jax.dynamics import mlp

TARGETS = ("v", "x0", "eps")


@dataclasses.dataclass(frozen=True)
class DiffusionConfig:
    """Denoiser size and parameterisation, schedule and the sampler's budget."""

    net: mlp.MLPConfig = mlp.MLPConfig()
    time_features: int = 8
    steps: int = 100  # noise levels of the training schedule
    nfe: int = 10  # denoising evaluations per sample (<= steps)
    eta: float = 0.0  # 0: deterministic DDIM, 1: ancestral
    clip: float = 5.0  # bound on the clean-sample estimate (normalised units)
    target: str = "v"  # what the network predicts: TARGETS
    abar_min: float = 1e-3  # signal fraction left at the noisiest level

    def __post_init__(self):
        if not 1 <= self.nfe <= self.steps:
            raise ValueError(f"nfe={self.nfe}: need 1 <= nfe <= steps={self.steps}")
        if not 0.0 <= self.eta <= 1.0:
            raise ValueError(f"eta={self.eta}: need 0 <= eta <= 1")
        if self.target not in TARGETS:
            raise ValueError(f"target {self.target!r} is not one of {TARGETS}")
        if not 0.0 < self.abar_min < 1.0:
            raise ValueError(f"abar_min={self.abar_min}: need 0 < abar_min < 1")


def alpha_bar(s: jax.Array, steps: int, abar_min: float = 1e-3) -> jax.Array:
    """Cumulative signal fraction at level ``s`` in ``0..steps``: a cosine schedule rescaled to
    run from 1 at ``s = 0`` to ``abar_min`` at ``s = steps``."""
    f = lambda u: jnp.cos((u + 0.008) / 1.008 * jnp.pi / 2) ** 2
    return abar_min + (1.0 - abar_min) * jnp.clip(f(s / steps) / f(0.0), 0.0, 1.0)


def _embedding(s: jax.Array, steps: int, n: int) -> jax.Array:
    freqs = jnp.pi * 2.0 ** jnp.arange(n // 2)
    u = s / steps
    return jnp.concatenate([jnp.sin(freqs * u), jnp.cos(freqs * u)])


def init(key: jax.Array, dim: int, context_dim: int, cfg: DiffusionConfig = DiffusionConfig()
         ) -> dict:
    """Parameters of the denoiser ``out_theta(x [dim], s | c [context_dim])``."""
    return mlp.mlp(cfg.net, dim, zero_last=True)[0](key, dim + cfg.time_features + context_dim)


def network(params: dict, x: jax.Array, s: jax.Array, context: jax.Array,
            cfg: DiffusionConfig = DiffusionConfig()) -> jax.Array:
    """The denoiser's raw output ``[dim]`` (``cfg.target``'s units)."""
    _, apply = mlp.mlp(cfg.net, x.shape[-1], zero_last=True)
    return apply(params, jnp.concatenate([x, _embedding(s, cfg.steps, cfg.time_features), context]))


def clean_and_noise(out: jax.Array, x: jax.Array, ab: jax.Array, cfg: DiffusionConfig
                    ) -> tuple[jax.Array, jax.Array]:
    """``(x0_hat, e_hat)`` from the network's output at ``x`` with signal fraction ``ab``: the
    clean estimate clipped to ``+-cfg.clip`` and the noise consistent with it."""
    a, b = jnp.sqrt(ab), jnp.sqrt(1.0 - ab)
    if cfg.target == "v":
        x0 = a * x - b * out
    elif cfg.target == "x0":
        x0 = out
    else:
        x0 = (x - b * out) / a
    x0 = jnp.clip(x0, -cfg.clip, cfg.clip)
    return x0, (x - a * x0) / b


def loss(params: dict, x0: jax.Array, context: jax.Array, key: jax.Array,
         cfg: DiffusionConfig = DiffusionConfig()) -> jax.Array:
    """The denoising loss of one example: ``|out_theta(x_s, s | c) - target|^2``."""
    key_s, key_e = jax.random.split(key)
    s = jax.random.randint(key_s, (), 1, cfg.steps + 1).astype(x0.dtype)
    e = jax.random.normal(key_e, x0.shape, x0.dtype)
    ab = alpha_bar(s, cfg.steps, cfg.abar_min)
    xs = jnp.sqrt(ab) * x0 + jnp.sqrt(1.0 - ab) * e
    target = {"v": jnp.sqrt(ab) * e - jnp.sqrt(1.0 - ab) * x0, "x0": x0, "eps": e}[cfg.target]
    return jnp.sum((network(params, xs, s, context, cfg) - target) ** 2)


def ddim(predict: Callable, x_init: jax.Array, key: jax.Array, cfg: DiffusionConfig, nfe: int,
         eta: float) -> jax.Array:
    """Denoises ``x_init`` (the noisiest level) in ``nfe`` DDIM updates; ``predict(x, s)`` is the
    network's raw output. ``eta = 0``: deterministic (``key`` unused)."""
    if not 1 <= nfe <= cfg.steps:
        raise ValueError(f"nfe={nfe}: need 1 <= nfe <= steps={cfg.steps}")
    levels = jnp.linspace(cfg.steps, 0, nfe + 1)  # s_0 = steps > ... > s_nfe = 0

    def update(x, inp):
        (s, s_next), k = inp
        ab, ab_next = alpha_bar(s, cfg.steps, cfg.abar_min), alpha_bar(s_next, cfg.steps,
                                                                       cfg.abar_min)
        x0, e = clean_and_noise(predict(x, s), x, ab, cfg)
        sigma = eta * jnp.sqrt((1 - ab_next) / (1 - ab) * (1 - ab / ab_next))
        direction = jnp.sqrt(jnp.clip(1.0 - ab_next - sigma ** 2, 0.0)) * e
        return jnp.sqrt(ab_next) * x0 + direction + sigma * jax.random.normal(k, x.shape,
                                                                              x.dtype), None

    x, _ = jax.lax.scan(update, x_init,
                        ((levels[:-1], levels[1:]), jax.random.split(key, nfe)))
    return x


def sample(params: dict, context: jax.Array, key: jax.Array, dim: int,
           cfg: DiffusionConfig = DiffusionConfig(), nfe: int | None = None,
           central: bool = False) -> jax.Array:
    """One sample ``[dim]`` given ``context``, denoised in ``nfe`` evaluations. ``central``:
    the deterministic DDIM map (``eta = 0``) of ``x = 0``, the diffusion's counterpart of
    ``flow.central`` (``key`` unused)."""
    key_x, key_noise = jax.random.split(key)
    x_init = jnp.zeros((dim,)) if central else jax.random.normal(key_x, (dim,))
    predict = lambda x, s: network(params, x, s, context, cfg)
    return ddim(predict, x_init, key_noise, cfg, nfe or cfg.nfe, 0.0 if central else cfg.eta)
