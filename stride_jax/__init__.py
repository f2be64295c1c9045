"""stride_jax: structured Lagrangian + flow-matching residual dynamics for robots, in JAX/MJX."""

from stride_jax import _env  # noqa: F401  (XLA flags before JAX initialises)

__version__ = "0.1.0"
