"""The physics face of a model (``stride_jax.dynamics.physics``): M, g, C qd, inverse and forward
dynamics agree with each other and with the textbook Euler-Lagrange terms, batch only through
vmap, and keep float64."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import stride_jax.dynamics as dyn

ARM = dyn.ModelSpec(nq=2, nv=2, floating_base=False, periodic=(True, False))
BASE = dyn.ModelSpec(nq=9, nv=8, floating_base=True)  # a floating base with two joints
CFG = dyn.StructuredConfig(net=dyn.MLPConfig(hidden=16, depth=2), mass_init=3.0)


def _model(spec, name="delan", cfg=CFG):
    model = dyn.make(name, spec, cfg=cfg)
    params = model.init(jax.random.key(0))
    # Perturb the zero-initialised residual so that it matters.
    params = jax.tree.map(lambda w: w + 0.1 * jax.random.normal(jax.random.key(1), w.shape),
                          params)
    return model, params


def _state(spec, seed=0):
    k1, k2, k3 = jax.random.split(jax.random.key(seed), 3)
    if spec.floating_base:
        quat = jax.random.normal(k1, (4,))
        q = jnp.concatenate([jnp.array([0.1, -0.2, 0.4]), quat / jnp.linalg.norm(quat),
                             jax.random.normal(k1, (spec.nq - 7,))])
    else:
        q = jax.random.uniform(k1, (spec.nq,), minval=-3.0, maxval=3.0)
    return q, jax.random.normal(k2, (spec.nv,)), jax.random.normal(k3, (spec.nv,))


def test_fixed_base_terms_are_the_textbook_euler_lagrange_terms():
    """With M from the model: ``C qd = dM/dt qd - 1/2 d/dq (qd^T M qd)`` and ``g = dV/dq``
    (derived here by plain jacobians, independently of the library's linearisation)."""
    model, params = _model(ARM)
    q, qd, qdd = _state(ARM)
    with jax.enable_x64(True):
        params64 = jax.tree.map(lambda x: x.astype(jnp.float64), params)
        q, qd, qdd = (x.astype(jnp.float64) for x in (q, qd, qdd))
        M = lambda q: dyn.mass_matrix(model, params64, q)  # noqa: E731
        dM = jax.jacfwd(M)(q)  # [nv, nv, nq]
        coriolis_ref = jnp.einsum("ijk,k,j->i", dM, qd, qd) - 0.5 * jnp.einsum(
            "jki,j,k->i", dM, qd, qd)
        gravity_ref = jax.grad(lambda q: dyn.potential_energy(model, params64, q))(q)
        np.testing.assert_allclose(dyn.coriolis(model, params64, q, qd), coriolis_ref,
                                   rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(dyn.gravity(model, params64, q), gravity_ref, rtol=1e-10)
        tau = dyn.inverse_dynamics(model, params64, q, qd, qdd)
        np.testing.assert_allclose(tau, M(q) @ qdd + coriolis_ref + gravity_ref, rtol=1e-10)
        assert tau.dtype == jnp.float64


@pytest.mark.parametrize("spec", [ARM, BASE], ids=["arm", "floating"])
def test_inverse_and_forward_dynamics_invert_each_other(spec):
    model, params = _model(spec)
    q, qd, qdd = _state(spec, 1)

    @jax.jit  # one program (op by op the floating base took 20 s on a 2-core CPU)
    def check(params, q, qd, qdd):
        tau = dyn.inverse_dynamics(model, params, q, qd, qdd)
        return dict(prior=dyn.forward_dynamics(model, params, q, qd, tau, residual=False),
                    bias=dyn.bias_force(model, params, q, qd),
                    split=dyn.coriolis(model, params, q, qd) + dyn.gravity(model, params, q),
                    at_rest=dyn.coriolis(model, params, q, jnp.zeros(spec.nv)),
                    forward=dyn.forward_dynamics(model, params, q, qd, tau),
                    terms=model.terms(params, q, qd, tau, jax.random.key(0)))

    out = check(params, q, qd, qdd)
    np.testing.assert_allclose(out["prior"], qdd, rtol=1e-3, atol=1e-3)
    # The split the model predicts: bias = C qd + g; C qd vanishes at rest.
    np.testing.assert_allclose(out["bias"], out["split"], rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(out["at_rest"], 0.0, atol=1e-6)
    # With the residual: the model's own acceleration (the MLP residual's force added).
    terms = out["terms"]
    np.testing.assert_allclose(out["forward"], terms["prior"] + terms["residual"],
                               rtol=1e-4, atol=1e-4)
    assert float(jnp.abs(terms["residual"]).max()) > 1e-3


def test_floating_base_gravity_is_the_weight_of_the_robot():
    """V = m g z + V_net(orientation, joints): the world-frame translational part of g(q) is the
    weight ``(0, 0, m g)`` whatever the networks learned."""
    model, params = _model(BASE)
    q, _, _ = _state(BASE, 2)
    np.testing.assert_allclose(dyn.gravity(model, params, q)[:3], [0.0, 0.0, 3.0 * 9.81],
                               rtol=1e-5, atol=1e-5)


def test_batches_go_through_vmap_with_a_clear_error_otherwise():
    model, params = _model(ARM)
    qs = jnp.zeros((5, 2))
    with pytest.raises(dyn.InputError, match=r"mass_matrix: q must have shape \(2,\) \(one "
                                             r"example; vmap over the batch\), got \(5, 2\)"):
        dyn.mass_matrix(model, params, qs)
    with pytest.raises(dyn.InputError, match="inverse_dynamics: qdd must have shape"):
        dyn.inverse_dynamics(model, params, qs[0], qs[0], qs)
    with pytest.raises(dyn.InputError, match="vmap over the batch"):  # the low-level maths too
        dyn.lagrangian.mass_matrix(params["lnn"], ARM, qs, CFG.lnn)
    assert jax.vmap(lambda q: dyn.mass_matrix(model, params, q))(qs).shape == (5, 2, 2)
    onn = dyn.make("onn", ARM, cfg=CFG)
    with pytest.raises(TypeError, match="no Lagrangian prior"):
        dyn.gravity(onn, onn.init(jax.random.key(0)), qs[0])


def test_non_finite_inputs_are_named_where_the_values_are_known():
    """Called eagerly, NaN or inf in any argument is an error naming it; under jit the values
    are unknown, so NaN goes through (as it would through any jitted maths)."""
    model, params = _model(ARM)
    q = jnp.zeros(2)
    with pytest.raises(dyn.InputError, match="forward_dynamics: tau holds NaN or inf"):
        dyn.forward_dynamics(model, params, q, q, q.at[1].set(jnp.inf))
    with pytest.raises(dyn.InputError, match="bias_force: qd holds NaN or inf"):
        dyn.bias_force(model, params, q, q.at[0].set(jnp.nan))
    out = jax.jit(lambda qd: dyn.forward_dynamics(model, params, q, qd, q))(q.at[0].set(jnp.nan))
    assert np.isnan(np.asarray(out)).any()


@pytest.mark.parametrize("name", [pytest.param("stride", marks=pytest.mark.slow), "delan",
                                  pytest.param("delan_prior", marks=pytest.mark.slow)])
# (STRIDE: the Lagrangian terms of delan's case plus the flow's integration; DeLaN with a prior:
# delan's terms plus the prior's; both in `make test-all`)
def test_float64_inputs_run_in_float64(name):
    """With ``jax_enable_x64`` and float64 inputs nothing is computed in float32 (the float32
    params are promoted): the terms, the acceleration and a step come out float64, and
    ``inverse(forward(tau)) = tau`` to float64 rounding."""
    cfg = dataclasses.replace(CFG, nfe=2)
    with jax.enable_x64(True):
        model, params = _model(BASE, name, cfg)
        q, qd, qdd = (x.astype(jnp.float64) for x in _state(BASE, 3))
        fns = {"M": lambda: dyn.mass_matrix(model, params, q),
               "g": lambda: dyn.gravity(model, params, q),
               "tau": lambda: dyn.inverse_dynamics(model, params, q, qd, qdd),
               "qdd": lambda: dyn.forward_dynamics(model, params, q, qd, qdd),
               "acc": lambda: model.acceleration(params, q, qd, qdd, jax.random.key(0)),
               "step": lambda: model.step(params, q, qd, jnp.zeros(8), jax.random.key(0))}
        for k, fn in fns.items():
            assert all(x.dtype == jnp.float64 for x in jax.tree.leaves(jax.jit(fn)())), k
            jaxpr = str(jax.make_jaxpr(fn)())
            assert "new_dtype=float32" not in jaxpr, k  # no cast down to float32
        tau = dyn.inverse_dynamics(model, params, q, qd, qdd)
        back = dyn.forward_dynamics(model, params, q, qd, tau, residual=False)
        np.testing.assert_allclose(back, qdd, rtol=1e-9, atol=1e-9)
