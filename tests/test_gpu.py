"""Checks only a GPU can make: the fused kernels compile to Triton calls, a G1-sized step at the
paper's network size runs as one kernel and equals XLA's, and float32 products round as
``tests/precision.py`` assumes. ``make test-gpu`` runs these with the kernel tests (which then
run both in the interpreter and compiled); elsewhere they are skipped."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from precision import assert_close, exact, rounded, roundoff
from test_fused_step import _robot, _states

from stride_jax.dynamics import flow, fused, mlp, models, stride

pytestmark = pytest.mark.gpu


def test_float32_products_round_as_the_tolerances_assume():
    """The tolerance model takes float32 products on a GPU to run in TF32: the measured error of
    a default-precision product against a float64 one must not exceed that model."""
    k = 256
    a = jax.random.normal(jax.random.key(0), (512, k))
    b = jax.random.normal(jax.random.key(1), (k, 512))
    exact = np.asarray(a, np.float64) @ np.asarray(b, np.float64)
    err = np.abs(np.asarray(jax.jit(jnp.dot)(a, b), np.float64) - exact)
    # |error| of one product of length k ~ u sqrt(k) |a||b| (unit-variance entries here)
    measured = float(np.sqrt(np.mean(err ** 2)) / np.sqrt(k))
    assert measured <= 2 * roundoff(), (measured, roundoff())


@pytest.mark.parametrize("name", ["jvp", "vjp", "flow_euler"])
def test_kernels_compile_to_triton_calls(name):
    params = mlp.mlp(mlp.MLPConfig(hidden=64, depth=3), 24)[0](jax.random.key(0), 24)
    x = jax.random.normal(jax.random.key(1), (256, 24))
    if name == "jvp":
        fn = jax.vmap(lambda x: fused.jvp(params, x, x))
    elif name == "vjp":
        fn = jax.vmap(lambda x: fused.vjp(params, x, x))
    else:
        cfg = flow.FlowConfig(net=mlp.MLPConfig(hidden=64, depth=3), nfe=2)
        flow_params = flow.flow_init(jax.random.key(0), 12, 12, cfg)
        fn = jax.vmap(lambda x: fused.flow_euler(flow_params, x[:12], x[12:], cfg.nfe,
                                                 cfg.time_features))
    hlo = jax.jit(fn).lower(x).compile().as_text()
    assert "triton" in hlo.lower(), f"{name}: no Triton call in the compiled program"


@pytest.mark.parametrize("hidden", [64, 256])
def test_g1_sized_steps_run_as_kernels_and_equal_xla(hidden):
    """G1's 29 joints: at 64 wide the whole step is one kernel; at the paper's 256 x 3 its
    weight tiles exceed an SM's shared memory, so the step takes the per-pass kernels
    (``models.whole_step_fits``). Both compile here and equal XLA's float32 step."""
    spec, act = _robot(29)
    cfg = stride.StructuredConfig(net=mlp.MLPConfig(hidden=hidden, depth=3), shared_lnn=True,
                                  learn_mass=True, mass_init=35.0)
    xla = models.make("stride", spec, act, cfg)
    fast = models.make("stride", spec, act, dataclasses.replace(cfg, kernel="pallas-step"))
    leaves, tree = jax.tree.flatten(xla.init(jax.random.key(1)))
    params = tree.unflatten([w + 0.05 * jax.random.normal(jax.random.key(i), w.shape)
                             for i, w in enumerate(leaves)])
    q, qd, ctrl, keys = _states(spec, 64)
    step = lambda m, p: jax.jit(jax.vmap(lambda *a: m.step(p, *a)))
    with exact():
        ref, moved = step(xla, params)(q, qd, ctrl, keys), step(xla, rounded(params))(q, qd, ctrl, keys)
    out = step(fast, params)(q, qd, ctrl, keys)
    jaxpr = str(jax.make_jaxpr(jax.vmap(lambda *a: fast.step(params, *a)))(q, qd, ctrl, keys))
    whole = models.whole_step_fits(spec.nv, hidden)
    assert whole == (hidden <= 64)
    assert ("stride_fused_step" in jaxpr) == whole and "stride_fused" in jaxpr
    hlo = step(fast, params).lower(q, qd, ctrl, keys).compile().as_text()
    assert "triton" in hlo.lower()
    acc_ref, acc = (ref[1] - qd) / act.dt, (out[1] - qd) / act.dt
    scale = jnp.max(jnp.abs(acc_ref), axis=1, keepdims=True)
    sens = jnp.max(jnp.abs((moved[1] - ref[1]) / act.dt) / scale)
    assert np.isfinite(np.asarray(out[1])).all()
    assert_close(acc / scale, acc_ref / scale, sensitivity=sens, floor=2e-5,
                 err_msg="acceleration / its row's scale")
