"""The one linear solve of a structured model step: ``M(q) qdd = f`` with M symmetric positive
definite and small (18 x 18 for Go1, 35 x 35 for G1), batched over a planner's rollouts.

On a CPU, XLA's batched Cholesky is a loop over the batch calling LAPACK on one small matrix at a
time (plus two triangular solves), which cost a 2-core MPPI step about a fifth of its model time.
:func:`spd_solve` runs Gauss-Jordan elimination instead, written with the batch as the *last*
axis so each of its ``n`` steps is one vectorised update of the whole batch: no pivoting is needed
for a symmetric positive definite matrix (its pivots are its Schur complements' diagonals, all
positive). Measured on this 2-core CPU (a batch of 128 18 x 18 systems,
``python experiments/probes/spd_solve_time.py``): LAPACK 0.37 ms, the same elimination vmapped (batch
first) 0.33 ms, batch last 0.17 ms; ``experiments/probes/model_step_time.py`` times the whole step.
GPUs keep cuSOLVER's batched Cholesky: ``n`` dependent steps would be ``n`` kernels there, where
the planner's time is bound by the number of kernels.

Gradients come from :func:`jax.lax.custom_linear_solve` (implicit differentiation: the solver is
only ever called, never differentiated), so the solve composes with ``grad``, ``jvp`` and
``vmap`` like ``cho_solve``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def _gauss_jordan(M: jax.Array, b: jax.Array) -> jax.Array:
    """``M^-1 b`` with the batch last: ``M [n, n, *batch]``, ``b [n, *batch]``."""
    n = M.shape[0]
    A = jnp.concatenate([M, b[:, None]], axis=1)  # [n, n + 1, *batch]
    rows = jnp.arange(n).reshape((n,) + (1,) * (A.ndim - 1))
    for j in range(n):  # static: n whole-batch updates
        pivot = A[j] / A[j, j]
        A = A - jnp.where(rows == j, 0.0, A[:, j:j + 1]) * pivot[None]
        A = A.at[j].set(pivot)
    return A[:, n]


@jax.custom_batching.custom_vmap
def _solve_cpu(M: jax.Array, b: jax.Array) -> jax.Array:
    return _gauss_jordan(M, b)


@_solve_cpu.def_vmap
def _solve_cpu_batched(axis_size, in_batched, M, b):
    M_batched, b_batched = in_batched
    M = M if M_batched else jnp.broadcast_to(M, (axis_size,) + M.shape)
    b = b if b_batched else jnp.broadcast_to(b, (axis_size,) + b.shape)
    # The vmapped axis goes last (inside an outer vmap the outer axis is handled by the ops).
    x = _gauss_jordan(jnp.moveaxis(M, 0, -1), jnp.moveaxis(b, 0, -1))
    return jnp.moveaxis(x, -1, 0), True


def _solve_cholesky(M: jax.Array, b: jax.Array) -> jax.Array:
    return jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(M), b)


def spd_solve(M: jax.Array, b: jax.Array) -> jax.Array:
    """``M^-1 b`` for a symmetric positive definite ``M [n, n]`` and ``b [n]``."""
    if M.ndim != 2 or M.shape != (b.shape[0],) * 2 or b.ndim != 1:
        raise ValueError(f"spd_solve needs M [n, n] and b [n], got {M.shape} and {b.shape}")

    def solve(_, rhs):
        return jax.lax.platform_dependent(M, rhs, cpu=_solve_cpu, default=_solve_cholesky)

    return jax.lax.custom_linear_solve(lambda x: M @ x, b, solve, symmetric=True)
