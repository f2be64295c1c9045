"""The one network every model is built from: a Flax MLP as an ``init``/``apply`` pair.

All models of the paper's comparison share widths and depths through :class:`MLPConfig`, so "same
size" is one config, not a convention.
"""

from __future__ import annotations

import dataclasses
import numbers
from typing import Any, Callable

import flax.linen as nn
import jax
import jax.numpy as jnp

# Names a config may give (a saved model's ``model.json`` holds the name, not the function).
ACTIVATIONS = {"silu": nn.silu, "tanh": nn.tanh, "relu": nn.relu, "gelu": nn.gelu,
               "softplus": nn.softplus, "elu": nn.elu}
PRODUCTS = {"float32": jnp.float32, "bfloat16": jnp.bfloat16}
INITS = {"lecun_normal": nn.initializers.lecun_normal, "glorot_normal":
         nn.initializers.glorot_normal, "glorot_uniform": nn.initializers.glorot_uniform,
         "he_normal": nn.initializers.he_normal, "orthogonal": nn.initializers.orthogonal}


@dataclasses.dataclass(frozen=True)
class MLPConfig:
    """Hidden width and number of hidden layers, the hidden layers' ``activation``
    (:data:`ACTIVATIONS`) and the weights' ``init`` (:data:`INITS`; biases start at zero).

    The fused inference kernels (``StructuredConfig.kernel``) implement SiLU only.

    Attributes:
      hidden: width of every hidden layer.
      depth: number of hidden layers.
      activation: the hidden layers' activation (``ACTIVATIONS``).
      init: the weights' initialisation (``INITS``; biases start at zero).
      products: the matrix products' input type, ``float32`` or ``bfloat16`` (rounded
        operands, float32 accumulation, biases and activations in float32). An inference
        choice (``StructuredConfig.kernel = "xla-bf16"`` sets it for every network): on a CPU
        with bfloat16 dot instructions (AVX512-BF16, AMX) the products run up to ~2x faster.
    """

    hidden: int = 256
    depth: int = 3
    activation: str = "silu"
    init: str = "lecun_normal"
    products: str = "float32"

    def __post_init__(self):
        for name in ("hidden", "depth"):
            value = getattr(self, name)
            if not isinstance(value, numbers.Integral) or isinstance(value, bool) or value < 1:
                raise ValueError(f"MLPConfig.{name} must be a positive integer, got {value!r}")
        if self.activation not in ACTIVATIONS:
            raise ValueError(f"MLPConfig.activation {self.activation!r} is not one of "
                             f"{', '.join(ACTIVATIONS)}")
        if self.init not in INITS:
            raise ValueError(f"MLPConfig.init {self.init!r} is not one of {', '.join(INITS)}")
        if self.products not in PRODUCTS:
            raise ValueError(f"MLPConfig.products {self.products!r} is not one of "
                             f"{', '.join(PRODUCTS)}")


class _MLP(nn.Module):
    hidden: int
    depth: int
    out: int
    activation: Callable = nn.silu
    kernel_init: Callable = nn.initializers.lecun_normal()
    zero_last: bool = False

    @nn.compact
    def __call__(self, x):
        for _ in range(self.depth):
            x = self.activation(nn.Dense(self.hidden, kernel_init=self.kernel_init)(x))
        init = nn.initializers.zeros if self.zero_last else self.kernel_init
        return nn.Dense(self.out, kernel_init=init)(x)


def mlp(cfg: MLPConfig, out: int, zero_last: bool = False) -> tuple[Callable, Callable]:
    """Returns ``(init(key, in_dim) -> params, apply(params, x [in_dim]) -> [out])``.

    ``zero_last`` starts the output at exactly zero (used for residuals and vector fields).
    """
    module = _MLP(cfg.hidden, cfg.depth, out, ACTIVATIONS[cfg.activation], INITS[cfg.init](),
                  zero_last=zero_last)

    def init(key: jax.Array, in_dim: int) -> Any:
        return module.init(key, jnp.zeros((in_dim,)))

    if cfg.products == "float32":
        return init, module.apply
    dtype, activation = PRODUCTS[cfg.products], ACTIVATIONS[cfg.activation]

    def apply(params: Any, x: jax.Array) -> jax.Array:
        """``module.apply`` with the products' operands rounded to ``dtype`` (same parameters)."""
        layers = params["params"]
        for i in range(cfg.depth + 1):
            dense = layers[f"Dense_{i}"]
            x = jnp.dot(x.astype(dtype), dense["kernel"].astype(dtype),
                        preferred_element_type=jnp.float32) + dense["bias"]
            if i < cfg.depth:
                x = activation(x)
        return x

    return init, apply
