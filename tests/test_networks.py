"""The learned pieces: an SPD mass matrix, and a flow that keeps both modes where MSE averages."""


import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from stride_jax.dynamics import diffusion, flow, generative, lagrangian, mlp, stride
from stride_jax.types import ModelSpec

GO1_SPEC = ModelSpec(nq=19, nv=18, floating_base=True)
PENDULUM_SPEC = ModelSpec(nq=1, nv=1, floating_base=False, periodic=(True,))


@pytest.mark.parametrize("spec", [GO1_SPEC, PENDULUM_SPEC], ids=["go1", "pendulum"])
def test_learned_mass_matrix_is_symmetric_positive_definite(spec):
    cfg = lagrangian.LNNConfig(net=mlp.MLPConfig(hidden=32, depth=2))
    with jax.enable_x64(True):  # eigenvalues of an ill-conditioned M need float64 to be trusted
        params = lagrangian.lnn_init(jax.random.key(0), spec, cfg)
        # Scale the weights up so that the check is not carried by near-zero raw outputs.
        params = jax.tree.map(lambda w: 2.0 * jnp.asarray(w, jnp.float64), params)
        qs = jax.random.normal(jax.random.key(1), (64, spec.nq), jnp.float64)
        if spec.floating_base:
            qs = qs.at[:, 3:7].set(qs[:, 3:7] / jnp.linalg.norm(qs[:, 3:7], axis=1, keepdims=True))
        M = np.asarray(jax.vmap(lambda q: lagrangian.mass_matrix(params, spec, q, cfg))(qs))
    np.testing.assert_allclose(M, np.swapaxes(M, 1, 2), atol=1e-12)
    assert np.linalg.eigvalsh(M).min() >= cfg.diag_floor * (1 - 1e-6)
    assert np.all(np.linalg.cholesky(M).diagonal(axis1=1, axis2=2) > 0)
    assert np.std(M) > 1e-2  # not a constant


def test_periodic_features_make_the_pendulum_model_periodic():
    cfg = lagrangian.LNNConfig(net=mlp.MLPConfig(hidden=16, depth=1))
    params = lagrangian.lnn_init(jax.random.key(0), PENDULUM_SPEC, cfg)
    V = lambda q: lagrangian.potential_energy(params, PENDULUM_SPEC, jnp.array([q]), cfg)
    assert float(V(0.3)) == pytest.approx(float(V(0.3 + 2 * np.pi)), abs=1e-5)
    assert float(V(0.3)) != pytest.approx(float(V(1.3)), abs=1e-5)


def _bimodal(key, n):
    """x = c + s with s = +-1 at equal odds, c ~ U(-1, 1): two modes, mean c."""
    key_c, key_s = jax.random.split(key)
    c = jax.random.uniform(key_c, (n, 1), minval=-1, maxval=1)
    s = jnp.where(jax.random.bernoulli(key_s, shape=(n, 1)), 1.0, -1.0)
    return c, c + s


@pytest.mark.parametrize("kind,nfe", [("flow", 8), ("diffusion", 20)])
def test_generators_keep_both_modes_where_mse_returns_the_mean(kind, nfe, run_time_bound):
    gen = generative.make(kind, mlp.MLPConfig(hidden=64, depth=2), nfe)
    params = gen.init(jax.random.key(0), 1, 1)
    reg_init, reg_apply = mlp.mlp(mlp.MLPConfig(hidden=64, depth=2), 1)
    reg = reg_init(jax.random.key(1), 1)
    opt = optax.adam(3e-3)
    state = opt.init((params, reg))

    def loss(p, key):
        params, reg = p
        key_d, key_f = jax.random.split(key)
        c, x = _bimodal(key_d, 256)
        keys = jax.random.split(key_f, 256)
        l_gen = jnp.mean(jax.vmap(lambda x1, ci, k: gen.loss(params, x1, ci, k))(x, c, keys))
        l_mse = jnp.mean((jax.vmap(lambda ci: reg_apply(reg, ci))(c) - x) ** 2)
        return l_gen + l_mse

    def step(i, carry):
        p, state = carry
        g = jax.grad(loss)(p, jax.random.key(100 + i))
        updates, state = opt.update(g, state)
        return optax.apply_updates(p, updates), state

    # every step in one program (1500 steps: run-time bound, and no dispatch per step)
    train = jax.jit(lambda p, state: jax.lax.fori_loop(0, 1500, step, (p, state)),
                    compiler_options=run_time_bound)
    params, reg = train((params, reg), state)[0]
    c = jnp.full((2000, 1), 0.25)
    x = jax.vmap(lambda ci, k: gen.sample(params, ci, k, 1))(c, jax.random.split(jax.random.key(7), 2000))
    dev = np.asarray(x - c)[:, 0]
    assert np.mean(dev > 0.5) > 0.3 and np.mean(dev < -0.5) > 0.3  # both modes
    assert np.mean(np.abs(dev) < 0.3) < 0.1  # little mass at the mean
    assert abs(float(reg_apply(reg, jnp.array([0.25]))[0]) - 0.25) < 0.2  # MSE: the mean


@pytest.mark.parametrize("bad", [dict(integrator="rk45"), dict(nfe=0), dict(integrator="midpoint", nfe=3)])
def test_bad_flow_configs_are_clear_errors(bad):
    with pytest.raises(ValueError, match="integrator|nfe"):
        flow.FlowConfig(**bad)


@pytest.mark.parametrize("bad", [dict(nfe=0), dict(nfe=101), dict(eta=2.0)])
def test_bad_diffusion_configs_are_clear_errors(bad):
    with pytest.raises(ValueError, match="nfe|eta"):
        diffusion.DiffusionConfig(**bad)


def test_diffusion_sampler_refuses_more_evaluations_than_levels():
    cfg = diffusion.DiffusionConfig(net=mlp.MLPConfig(hidden=8, depth=1))
    params = diffusion.init(jax.random.key(0), 2, 1, cfg)
    with pytest.raises(ValueError, match="nfe"):
        diffusion.sample(params, jnp.zeros(1), jax.random.key(0), 2, cfg, nfe=500)


def test_untrained_flow_is_the_identity_transport():
    cfg = flow.FlowConfig(net=mlp.MLPConfig(hidden=8, depth=1), integrator="midpoint", nfe=4)
    params = flow.flow_init(jax.random.key(0), 3, 2, cfg)
    z0 = jnp.ones(3)
    # The field starts at exactly zero, so the transport is the identity.
    np.testing.assert_allclose(flow.integrate(params, z0, jnp.zeros(2), cfg), z0)


@pytest.mark.parametrize("shared", [False, True], ids=["two-nets", "shared"])
@pytest.mark.parametrize("spec", [GO1_SPEC, PENDULUM_SPEC], ids=["go1", "pendulum"])
def test_feature_space_lagrangian_terms_equal_the_reference(spec, shared):
    """``lnn_terms`` (derivatives split at the networks' features) equals ``bias_force`` through
    the retraction, for a floating base with a gravity term and for periodic hinge features,
    with L and V from two networks or from one."""
    cfg = lagrangian.LNNConfig(net=mlp.MLPConfig(hidden=32, depth=2), mass_init=12.0,
                               shared=shared)
    with jax.enable_x64(True):
        params = jax.tree.map(lambda w: 2.0 * jnp.asarray(w, jnp.float64),
                              lagrangian.lnn_init(jax.random.key(0), spec, cfg))
        qs = jax.random.normal(jax.random.key(1), (8, spec.nq), jnp.float64)
        if spec.floating_base:
            qs = qs.at[:, 3:7].set(qs[:, 3:7] / jnp.linalg.norm(qs[:, 3:7], axis=1, keepdims=True))
        vs = 2.0 * jax.random.normal(jax.random.key(2), (8, spec.nv), jnp.float64)
        # one program each (op by op, go1's two-net variant took 16 s on a 2-core CPU)
        fast = jax.jit(jax.vmap(lambda q, v: lagrangian.lnn_terms(params, spec, q, v, cfg)))(
            qs, vs)
        ref = jax.jit(jax.vmap(lambda q, v: lagrangian.lnn_terms_reference(params, spec, q, v,
                                                                           cfg)))(qs, vs)
    for a, b in zip(fast, ref):
        assert np.abs(np.asarray(b)).max() > 1e-3  # not trivially zero
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-9, atol=1e-9)
    assert set(params) == ({"shared"} if shared else {"mass", "potential"}) | (
        {"log_mass"} if cfg.learn_mass else set())


def test_default_activation_and_init_are_the_original_network():
    """``MLPConfig()``'s SiLU and LeCun-normal init give bitwise the network of earlier versions
    (a plain Flax MLP with Dense's defaults), so saved runs and results stay the same; other
    choices change it; unknown names and sizes are clear errors."""
    import flax.linen as nn

    class Original(nn.Module):
        @nn.compact
        def __call__(self, x):
            for _ in range(2):
                x = nn.silu(nn.Dense(16)(x))
            return nn.Dense(3)(x)

    key, x = jax.random.key(0), jnp.linspace(-1.0, 1.0, 5)
    init, apply = mlp.mlp(mlp.MLPConfig(16, 2), 3)
    params = init(key, 5)
    want = Original().init(key, jnp.zeros(5))
    assert jax.tree.all(jax.tree.map(lambda a, b: bool((a == b).all()), params, want))
    np.testing.assert_array_equal(apply(params, x), Original().apply(want, x))
    init_t, apply_t = mlp.mlp(mlp.MLPConfig(16, 2, activation="tanh", init="orthogonal"), 3)
    params_t = init_t(key, 5)
    assert not np.allclose(params_t["params"]["Dense_0"]["kernel"],
                           params["params"]["Dense_0"]["kernel"])
    assert not np.allclose(apply_t(params, x), apply(params, x))  # tanh in place of SiLU
    with pytest.raises(ValueError, match="activation 'swish' is not one of silu"):
        mlp.MLPConfig(activation="swish")
    with pytest.raises(ValueError, match="hidden must be a positive integer"):
        mlp.MLPConfig(hidden=0)
    with pytest.raises(ValueError, match="SiLU networks only"):
        stride.StructuredConfig(net=mlp.MLPConfig(activation="tanh"), kernel="pallas")


@pytest.mark.parametrize("floor", [0.0, -1e-3, float("nan"), float("inf"), "1e-3"])
def test_a_wrong_diag_floor_is_refused(floor):
    with pytest.raises(ValueError, match="diag_floor must be a finite number > 0"):
        lagrangian.LNNConfig(diag_floor=floor)
    with pytest.raises(ValueError, match="diag_floor"):
        stride.StructuredConfig(diag_floor=floor)


def test_bfloat16_products_are_the_same_network_rounded():
    """``products="bfloat16"`` runs the same parameters with the products' operands rounded to
    bfloat16 (float32 accumulation): the outputs equal float32's to bfloat16's precision (8-bit
    significand: relative error ~2^-8 per operand, a few such over three layers), differ from
    them (the rounding is real), and differentiate; unknown types are refused."""
    cfg = mlp.MLPConfig(64, 3)
    init, apply = mlp.mlp(cfg, 4)
    _, apply_bf = mlp.mlp(mlp.MLPConfig(64, 3, products="bfloat16"), 4)
    params = jax.tree.map(lambda w: w + 0.1 * jax.random.normal(jax.random.key(2), w.shape),
                          init(jax.random.key(1), 8))
    x = jax.random.normal(jax.random.key(3), (32, 8))
    want, got = jax.vmap(lambda v: apply(params, v))(x), jax.vmap(lambda v: apply_bf(params, v))(x)
    assert got.dtype == jnp.float32
    rel = float(jnp.linalg.norm(got - want) / jnp.linalg.norm(want))
    assert 1e-4 < rel < 3e-2, rel
    g = jax.grad(lambda p: jnp.sum(apply_bf(p, x[0]) ** 2))(params)
    g32 = jax.grad(lambda p: jnp.sum(apply(p, x[0]) ** 2))(params)
    for a, b in zip(jax.tree.leaves(g), jax.tree.leaves(g32)):
        np.testing.assert_allclose(a, b, rtol=0.1, atol=0.05 * float(jnp.abs(b).max()) + 1e-6)
    with pytest.raises(ValueError, match="products 'float16' is not one of float32"):
        mlp.MLPConfig(products="float16")
