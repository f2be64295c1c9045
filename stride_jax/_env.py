"""Process-level XLA settings that must be in place before JAX initialises.

``stride_jax/__init__.py`` imports this module first, so any ``import stride_jax`` before the first
``import jax`` is enough.
"""

import os

# On small CPUs, XLA's concurrency-optimised scheduler deadlocks inside the batched Cholesky that
# vmapped MJX steps use (batch >= 16 on a 2-core machine, reproduced with jax 0.10.2). The user's
# own XLA_FLAGS win: we only add the flag when they set none.
CPU_SAFE_XLA_FLAGS = "--xla_cpu_enable_concurrency_optimized_scheduler=false"

if "XLA_FLAGS" not in os.environ:
    os.environ["XLA_FLAGS"] = CPU_SAFE_XLA_FLAGS
