"""The structured models' linear solve: Gauss-Jordan with the batch last on CPUs, Cholesky
elsewhere; equal to ``cho_solve`` in value and in derivatives, under ``vmap`` of any depth."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from stride_jax.dynamics import linalg


def _cholesky(M, b):
    return jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(M), b)


def _systems(batch, n=18):
    A = jax.random.normal(jax.random.key(0), batch + (n, n))
    b = jax.random.normal(jax.random.key(1), batch + (n,))
    return A, b


def _spd(A):
    # L L^T plus a floor, as the learned mass matrix: condition numbers in the hundreds.
    return A @ jnp.swapaxes(A, -1, -2) + 0.1 * jnp.eye(A.shape[-1])


@pytest.mark.parametrize("batch", [(), (64,), (4, 16)], ids=["one", "vmap", "nested-vmap"])
def test_spd_solve_equals_cholesky(batch):
    A, b = _systems(batch)
    M = _spd(A)
    solve, ref = linalg.spd_solve, _cholesky
    for _ in batch:
        solve, ref = jax.vmap(solve), jax.vmap(ref)
    x = jax.jit(solve)(M, b)
    np.testing.assert_allclose(x, ref(M, b), rtol=2e-3, atol=2e-4)
    np.testing.assert_allclose(jnp.einsum("...ij,...j->...i", M, x), b, atol=2e-3)


def test_spd_solve_broadcasts_an_unbatched_operand_under_vmap():
    A, b = _systems((8,))
    M = _spd(A[0])
    x = jax.vmap(linalg.spd_solve, in_axes=(None, 0))(M, b)
    np.testing.assert_allclose(x, jax.vmap(lambda r: _cholesky(M, r))(b), rtol=2e-3, atol=2e-4)


def test_spd_solve_derivatives_equal_choleskys():
    """Through a symmetric M (as the models build it), reverse and forward mode."""
    A, b = _systems((16,))

    def loss(solve, A, b):
        return jnp.sum(jnp.sin(jax.vmap(solve)(_spd(A), b)))

    for argnum in (0, 1):
        g = jax.grad(lambda *a: loss(linalg.spd_solve, *a), argnums=argnum)(A, b)
        g_ref = jax.grad(lambda *a: loss(_cholesky, *a), argnums=argnum)(A, b)
        np.testing.assert_allclose(g, g_ref, rtol=1e-2, atol=1e-3 * float(jnp.abs(g_ref).max()))
    t = jax.jvp(lambda A: loss(linalg.spd_solve, A, b), (A,), (jnp.ones_like(A),))[1]
    t_ref = jax.jvp(lambda A: loss(_cholesky, A, b), (A,), (jnp.ones_like(A),))[1]
    np.testing.assert_allclose(t, t_ref, rtol=1e-2)


@pytest.mark.parametrize("shapes", [((3, 4), (3,)), ((3, 3), (4,)), ((3, 3), (3, 1))])
def test_spd_solve_bad_shapes_are_clear_errors(shapes):
    with pytest.raises(ValueError, match="spd_solve needs"):
        linalg.spd_solve(jnp.ones(shapes[0]), jnp.ones(shapes[1]))
