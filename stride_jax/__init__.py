"""stride_jax: structured Lagrangian + flow-matching residual dynamics for robots, in JAX/MJX.

Importing the package sets nothing in the process; entry points call :func:`set_xla_flags`
(small CPUs deadlock in XLA without its flags; see ``stride_jax/_env.py``).
"""

from stride_jax._env import CPU_SAFE_XLA_FLAGS, set_xla_flags

__version__ = "0.1.0"

__all__ = ["CPU_SAFE_XLA_FLAGS", "set_xla_flags"]
