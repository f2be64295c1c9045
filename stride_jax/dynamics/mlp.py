"""The one network every model is built from: a Flax MLP as an ``init``/``apply`` pair.

All models of the paper's comparison share widths and depths through :class:`MLPConfig`, so "same
size" is one config, not a convention.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

import flax.linen as nn
import jax
import jax.numpy as jnp


@dataclasses.dataclass(frozen=True)
class MLPConfig:
    """Hidden width and number of hidden layers; SiLU activations."""

    hidden: int = 256
    depth: int = 3


class _MLP(nn.Module):
    hidden: int
    depth: int
    out: int
    activation: Callable = nn.silu
    zero_last: bool = False

    @nn.compact
    def __call__(self, x):
        for _ in range(self.depth):
            x = self.activation(nn.Dense(self.hidden)(x))
        init = nn.initializers.zeros if self.zero_last else nn.initializers.lecun_normal()
        return nn.Dense(self.out, kernel_init=init)(x)


def mlp(cfg: MLPConfig, out: int, zero_last: bool = False) -> tuple[Callable, Callable]:
    """Returns ``(init(key, in_dim) -> params, apply(params, x [in_dim]) -> [out])``.

    ``zero_last`` starts the output at exactly zero (used for residuals and vector fields).
    """
    module = _MLP(cfg.hidden, cfg.depth, out, zero_last=zero_last)

    def init(key: jax.Array, in_dim: int) -> Any:
        return module.init(key, jnp.zeros((in_dim,)))

    return init, module.apply
