"""Training on a robot given only as arrays (``stride_jax.train.fit``): DeLaN's prior learns a
pendulum's exact dynamics from samples of them."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import stride_jax.dynamics as dyn
from stride_jax.train import fit, loop


def _pendulum(n, seed=0):
    """A unit pendulum (m = l = 1, g = 9.81): ``tau = qdd + 9.81 sin q``, with no Coriolis."""
    rng = np.random.default_rng(seed)
    q = rng.uniform(-np.pi, np.pi, (n, 1))
    qd, qdd = rng.normal(size=(n, 1)), rng.normal(size=(n, 1))
    return q, qd, qdd + 9.81 * np.sin(q), qdd


def test_the_prior_learns_a_pendulum_from_arrays(tmp_path):
    q, qd, tau, qdd = _pendulum(2000)
    model, params = fit(q, qd, tau, qdd, tmp_path / "run", periodic=(True,),
                        config=dyn.StructuredConfig(net=dyn.MLPConfig(32, 2)),
                        loop_cfg=loop.LoopConfig(steps=600, batch=128, lr=3e-3,
                                                 eval_every=100), log=lambda _: None)
    assert model.name == "delan_prior"
    loaded, params = dyn.load(tmp_path / "run")  # the run folder is all it needs
    qs = jnp.linspace(-3.0, 3.0, 13)[:, None]
    g = jax.vmap(lambda q: dyn.gravity(loaded, params, q))(qs)
    M = jax.vmap(lambda q: dyn.mass_matrix(loaded, params, q))(qs)
    np.testing.assert_allclose(g, 9.81 * np.sin(qs), atol=0.3)  # measured: 0.044 at worst
    np.testing.assert_allclose(M[:, 0, 0], 1.0, atol=0.05)  # measured: 0.016 at worst


def test_bad_arrays_are_clear_errors(tmp_path):
    q, qd, tau, qdd = _pendulum(10)
    with pytest.raises(ValueError, match=r"fit: tau must have shape \[N, n\]"):
        fit(q, qd, tau[:5], qdd, tmp_path)
    with pytest.raises(ValueError, match="fit: qd holds NaN"):
        fit(q, np.full_like(qd, np.nan), tau, qdd, tmp_path)
    with pytest.raises(ValueError, match="fit trains the structured models"):
        fit(q, qd, tau, qdd, tmp_path, model="onn")
