"""The fused network kernels equal JAX's own derivatives of the Flax networks: in Pallas'
interpreter everywhere, and compiled on a GPU (the ``kernels`` fixture), within tolerances
derived from the precision of the products (``tests/precision.py``; TF32 on a GPU). The GPU
timings are in results/mppi_latency/README.md."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from precision import assert_close, exact, rounded

from stride_jax.dynamics import flow, fused, mlp, models, stride
from stride_jax.types import ModelSpec

# 40 samples: not a multiple of the kernel's rows; widths 21 -> 96 (two chunks) -> 37 (padded)
NET = mlp.MLPConfig(hidden=96, depth=2)
N, D_IN, D_OUT = 40, 21, 37
LAYERS = NET.depth + 1  # matrix products on a pass's longest path


@pytest.fixture(scope="module")
def net():
    init, apply = mlp.mlp(NET, D_OUT)
    params = init(jax.random.key(0), D_IN)
    keys = jax.random.split(jax.random.key(1), 3)
    x = jax.random.normal(keys[0], (N, D_IN))
    t = jax.random.normal(keys[1], (N, D_IN))
    g = jax.random.normal(keys[2], (N, D_OUT))
    return params, apply, x, t, g


def _reference(params, apply, x, t, g):
    y, yt = jax.vmap(lambda x, t: jax.jvp(lambda x: apply(params, x), (x,), (t,)))(x, t)
    gx = jax.vmap(lambda x, g: jax.vjp(lambda x: apply(params, x), x)[1](g)[0])(x, g)
    return y, yt, gx


def _fused(params, x, t, g):
    y, yt = jax.jit(jax.vmap(lambda x, t: fused.jvp(params, x, t)))(x, t)
    gx = jax.jit(jax.vmap(lambda x, g: fused.vjp(params, x, g)))(x, g)
    return y, yt, gx


def test_network_passes_match_autodiff(net, kernels):
    params, apply, x, t, g = net
    ref = _reference(params, apply, x, t, g)
    with kernels():
        out = _fused(params, x, t, g)
    for name, r, o in zip(("outputs", "tangent", "cotangent"), ref, out):
        assert_close(o, r, layers=LAYERS, floor=1e-5, err_msg=name)


def test_outside_a_kernel_context_the_batched_maths_is_plain_jax(net):
    """On a CPU the vmapped call is the batched maths in plain JAX (on a GPU, the kernel)."""
    params, apply, x, t, g = net
    for name, r, o in zip(("outputs", "tangent", "cotangent"), _reference(params, apply, x, t, g),
                          _fused(params, x, t, g)):
        assert_close(o, r, layers=LAYERS, floor=1e-5, err_msg=name)


def test_one_example_and_broadcast_inputs(net, kernels):
    """Unbatched, a pass is the plain network; a tangent shared by the batch is broadcast."""
    params, apply, x, t, g = net
    y, yt = fused.jvp(params, x[0], t[0])
    ref_y, ref_yt = jax.jvp(lambda x: apply(params, x), (x[0],), (t[0],))
    assert_close(y, ref_y, layers=LAYERS, floor=1e-6)
    assert_close(yt, ref_yt, layers=LAYERS, floor=1e-6)
    with kernels():
        _, yt_shared = jax.vmap(lambda x: fused.jvp(params, x, t[0]))(x)
    ref_shared = jax.vmap(lambda x: jax.jvp(lambda x: apply(params, x), (x,), (t[0],))[1])(x)
    assert_close(yt_shared, ref_shared, layers=LAYERS, floor=1e-5)


def test_per_sample_weights_fall_back_to_the_reference(net, kernels):
    """Weights batched with the inputs (an ensemble) cannot share one kernel: vmapped maths."""
    params, apply, x, _, g = net
    stacked = jax.tree.map(lambda w: jnp.stack([w, 2 * w]), params)
    with kernels():
        gx = jax.vmap(lambda p, x, g: fused.vjp(p, x, g))(stacked, x[:2], g[:2])
    p2 = jax.tree.map(lambda w: 2 * w, params)
    ref = jax.vjp(lambda x: apply(p2, x), x[1])[1](g[1])[0]
    assert_close(gx[1], ref, layers=LAYERS, floor=1e-5)


@pytest.mark.parametrize("nfe", [2])
def test_flow_sample_matches_the_integrator(nfe, kernels):
    cfg = flow.FlowConfig(net=NET, nfe=nfe)
    dim, c_dim = 18, 30
    params = flow.flow_init(jax.random.key(2), dim, c_dim, cfg)
    # the field starts at zero: perturb every weight so that the test sees the network
    params = jax.tree.map(lambda w: w + 0.1 * jax.random.normal(jax.random.key(3), w.shape),
                          params)
    z0 = jax.random.normal(jax.random.key(4), (N, dim))
    c = jax.random.normal(jax.random.key(5), (N, c_dim))
    ref = jax.vmap(lambda z, c: flow.integrate(params, z, c, cfg))(z0, c)
    with kernels():
        z = jax.jit(jax.vmap(lambda z, c: fused.flow_euler(params, z, c, nfe,
                                                           cfg.time_features)))(z0, c)
    assert float(jnp.max(jnp.abs(ref - z0))) > 0.1  # the field moved the samples
    # each Euler step is one pass of the field; the samples carry every step's error
    assert_close(z, ref, layers=nfe * (NET.depth + 1), floor=1e-5)


def test_bad_arguments():
    params = mlp.mlp(NET, 4)[0](jax.random.key(0), 3)
    with pytest.raises(ValueError, match="nfe >= 1"):
        fused.flow_euler(params, jnp.zeros(4), jnp.zeros(3), 0, 8)


@pytest.mark.parametrize("shared", [True, False], ids=["one-network", "two-networks"])
def test_model_steps_with_fused_kernels_equal_xla(shared, kernels):
    """A batch of model steps (a planner's rollouts) through the fused kernels gives XLA's
    next states; the training loss still differentiates (it always runs in XLA)."""
    spec = ModelSpec(nq=10, nv=9, floating_base=True)  # a floating base with three joints
    act = models.Actuation(dof=(6, 7, 8), kp=(20.0,) * 3, kd=(0.5,) * 3,
                           force_range=((-5.0, 5.0),) * 3, dt=0.01, n_substeps=1)
    cfg = stride.StructuredConfig(net=mlp.MLPConfig(hidden=16, depth=1), shared_lnn=shared)
    xla = models.make("stride", spec, act, cfg)
    fast = models.make("stride", spec, act, dataclasses.replace(cfg, kernel="pallas"))
    params = jax.tree.map(lambda w: w + 0.05 * jax.random.normal(jax.random.key(1), w.shape),
                          xla.init(jax.random.key(0)))
    n = 16
    keys = jax.random.split(jax.random.key(2), n)
    q = jnp.zeros((n, 10)).at[:, 2].set(0.3).at[:, 3].set(1.0)
    q = q.at[:, 7:].set(0.3 * jax.random.normal(jax.random.key(3), (n, 3)))
    qd = 0.5 * jax.random.normal(jax.random.key(4), (n, 9))
    ctrl = 0.2 * jax.random.normal(jax.random.key(5), (n, 3))
    with exact():  # the float32 reference (tests/precision.py)
        ref = jax.jit(jax.vmap(lambda *a: xla.step(params, *a)))(q, qd, ctrl, keys)
        moved = jax.jit(jax.vmap(lambda *a: xla.step(rounded(params), *a)))(q, qd, ctrl, keys)
    with kernels():
        out = jax.jit(jax.vmap(lambda *a: fast.step(params, *a)))(q, qd, ctrl, keys)
    assert float(jnp.max(jnp.abs(ref[1] - qd))) > 1e-3  # the step moved the state
    # compare the step's change of state (the state itself is exact on both sides); a solve
    # follows the products, so the tolerance is how far XLA's step moves with its weights
    # rounded to the products' precision (tests/precision.py)
    for name, r, o, m, s in zip(("q", "qd"), ref, out, moved, (q, qd)):
        assert_close(o - s, r - s, sensitivity=jnp.max(jnp.abs(m - r)), floor=1e-5,
                     err_msg=name)
    if not shared:
        return
    ex = dict(q=q[0], qd=qd[0], tau=jnp.zeros(9), qdd=jnp.ones(9), ctrl=ctrl[0],
              q_next=ref[0][0], qd_next=ref[1][0])
    # traced only (test_models runs the gradients): the fused kernels are not differentiable,
    # so this would fail if the loss reached them
    jax.make_jaxpr(jax.grad(lambda p: fast.loss(p, ex, keys[0])[0]))(params)


def test_bad_kernel_choices():
    with pytest.raises(ValueError, match="unknown kernel 'cuda'"):
        stride.StructuredConfig(kernel="cuda")
    with pytest.raises(ValueError, match="Euler steps only"):
        flow.FlowConfig(kernel="pallas", integrator="midpoint")


def test_transposed_pass_reads_wide_weight_tiles_in_pieces(kernels):
    """An output wider than ``OUT_CHUNK`` (G1's mass network: 627 outputs) is transposed in
    pieces of the weight tiles (whole, they exceed an SM's shared memory in float32)."""
    from stride_jax.dynamics import fused_pallas

    d_out = 2 * fused_pallas.OUT_CHUNK + 11  # padded to 4 pieces
    params = mlp.mlp(mlp.MLPConfig(hidden=32, depth=1), d_out)[0](jax.random.key(0), D_IN)
    apply = mlp.mlp(mlp.MLPConfig(hidden=32, depth=1), d_out)[1]
    x = jax.random.normal(jax.random.key(1), (16, D_IN))
    g = jax.random.normal(jax.random.key(2), (16, d_out))
    ref = jax.vmap(lambda x, g: jax.vjp(lambda x: apply(params, x), x)[1](g)[0])(x, g)
    with kernels():
        out = jax.jit(jax.vmap(lambda x, g: fused.vjp(params, x, g)))(x, g)
    assert_close(out, ref, layers=2, floor=1e-4)
