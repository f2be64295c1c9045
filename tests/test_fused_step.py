"""The whole model step as one kernel (``fused_step``) equals the XLA step: in Pallas'
interpreter everywhere and compiled on a GPU (the ``kernels`` fixture), within tolerances derived
from the products' precision (``tests/precision.py``). The GPU timings are in results/mppi_latency/README.md."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from precision import assert_close, exact, rounded

from stride_jax.dynamics import fused, fused_step, mlp, models, stride
from stride_jax.types import ModelSpec


def _robot(n_joints: int):
    nv = 6 + n_joints
    spec = ModelSpec(nq=nv + 1, nv=nv, floating_base=True, periodic=(False,) * n_joints)
    # mixed gains; the last joint's servo unlimited (an empty force range)
    ranges = ((-6.0, 6.0),) * (n_joints - 1) + ((0.0, 0.0),)
    act = models.Actuation(dof=tuple(range(6, nv)), kp=tuple(np.linspace(15, 30, n_joints)),
                           kd=tuple(np.linspace(0.3, 0.8, n_joints)), force_range=ranges,
                           dt=0.01, n_substeps=1)
    return spec, act


def _states(spec, n: int, seed: int = 0):
    keys = jax.random.split(jax.random.key(seed), 5)
    q = jnp.zeros((n, spec.nq)).at[:, 2].set(0.3)
    q = q.at[:, 3:7].set(jax.random.normal(keys[0], (n, 4)))  # any orientation
    q = q.at[:, 3:7].set(q[:, 3:7] / jnp.linalg.norm(q[:, 3:7], axis=1, keepdims=True))
    q = q.at[:, 7:].set(0.4 * jax.random.normal(keys[1], (n, spec.nv - 6)))
    qd = 1.5 * jax.random.normal(keys[2], (n, spec.nv))
    ctrl = q[:, 7:] + 0.5 * jax.random.normal(keys[3], (n, spec.nv - 6))  # some saturate
    return q, qd, ctrl, jax.random.split(keys[4], n)


@pytest.mark.parametrize("kernel, rows, block, joints, split", [
    ("pallas-step", 16, 1, 12, True), ("pallas-step-bf16", 8, 1, 12, False),
    # columns per loop iteration: Go1's 15 reduced dofs split 8 + 7, in blocks of 4 (two; one and
    # a rest of 3) and 2 (four; three and a rest of 1), unsplit in blocks of 4 (three and a rest
    # of 3); 18 dofs' products in blocks of 4 (four and a rest of 2)
    ("pallas-step-bf16", 8, 4, 12, True), ("pallas-step", 16, 2, 12, True),
    ("pallas-step-bf16", 8, 4, 12, False),
    # G1's size: 35 dofs, 32 reduced (no padding) split 16 + 16
    ("pallas-step-bf16", 8, 4, 29, True)])
def test_whole_step_equals_the_xla_step(kernels, kernel, rows, block, joints, split, monkeypatch):
    """Servo (saturated and unlimited joints), features, the prior's networks and products, the
    flow sample, the solve and the integration: the kernel's next states are XLA's (a Go1-sized
    and a G1-sized robot, a learned mass), in programs of either size ``program_rows`` chooses,
    with the small loops taking one or several columns per iteration (``fused_step.BLOCK``) and
    the reduced system factorised whole or in two halves (``fused_step.SPLIT``)."""
    monkeypatch.setattr(fused_step, "ROWS", rows)
    monkeypatch.setattr(fused_step, "BLOCK", dict.fromkeys(
        ("products", "gram", "factor", "backward"), block))
    monkeypatch.setattr(fused_step, "SPLIT", split)
    spec, act = _robot(joints)
    scales = stride.Scales(qd=jnp.linspace(0.5, 2.0, spec.nv), tau=jnp.linspace(1.0, 3.0, spec.nv),
                           force=jnp.linspace(2.0, 4.0, spec.nv))
    cfg = stride.StructuredConfig(net=mlp.MLPConfig(hidden=32, depth=2), shared_lnn=True,
                                  learn_mass=True, mass_init=5.0)
    xla = models.make("stride", spec, act, cfg, scales)
    fast = models.make("stride", spec, act, dataclasses.replace(cfg, kernel=kernel), scales)
    noise = lambda w, k: w + 0.1 * jax.random.normal(k, w.shape)
    leaves, tree = jax.tree.flatten(xla.init(jax.random.key(1)))
    params = tree.unflatten([noise(w, jax.random.key(i)) for i, w in enumerate(leaves)])
    q, qd, ctrl, keys = _states(spec, 20)  # not a multiple of the programs' rows
    step = lambda m: jax.jit(jax.vmap(lambda *a: m.step(params, *a)))
    dtype = fused.kernel_dtype(kernel)
    rounded_params = rounded(params, dtype)  # to the kernel's precision: outside exact()
    with exact():  # the float32 reference and its change with rounded weights (precision.py)
        ref = step(xla)(q, qd, ctrl, keys)
        moved = jax.jit(jax.vmap(lambda *a: xla.step(rounded_params, *a)))(q, qd, ctrl, keys)
    with kernels():
        jaxpr = jax.make_jaxpr(jax.vmap(lambda *a: fast.step(params, *a)))(q, qd, ctrl, keys)
        out = step(fast)(q, qd, ctrl, keys)
    assert "stride_fused_step" in str(jaxpr)  # the whole step ran as the kernel
    acc_ref, acc = (ref[1] - qd) / act.dt, (out[1] - qd) / act.dt
    scale = jnp.max(jnp.abs(acc_ref), axis=1, keepdims=True)
    assert float(jnp.min(scale)) > 1.0  # the steps accelerate
    # the products feed M, the bias and the flow and a solve follows: the tolerance is how far
    # the XLA step itself moves when its weights are rounded to the kernel's precision
    # one number for all rows: each row's rounding is one draw of the same random error
    sens = jnp.max(jnp.abs((moved[1] - ref[1]) / act.dt) / scale)
    assert_close(acc / scale, acc_ref / scale, sensitivity=sens, dtype=dtype, floor=2e-5,
                 err_msg="acceleration / its row's scale")
    assert_close(out[0] - q, ref[0] - q, dtype=dtype,
                 sensitivity=jnp.max(jnp.abs(moved[0] - ref[0])),
                 floor=1e-5, err_msg="change of position")
    np.testing.assert_allclose(jnp.linalg.norm(out[0][:, 3:7], axis=1), 1.0, atol=1e-6)


def test_whole_step_only_where_it_applies():
    """A model the whole step does not cover (two networks for L and V) takes the per-pass
    kernels; on a CPU, outside the interpreter, the step is the XLA step."""
    spec, act = _robot(3)
    q, qd, ctrl, keys = _states(spec, 4)
    net = mlp.MLPConfig(hidden=16, depth=1)
    two = stride.StructuredConfig(net=net, shared_lnn=False, kernel="pallas-step")
    model = models.make("stride", spec, act, two)
    params = model.init(jax.random.key(0))
    jaxpr = jax.make_jaxpr(jax.vmap(lambda *a: model.step(params, *a)))(q, qd, ctrl, keys)
    assert "stride_fused_mlp" in str(jaxpr) and "stride_fused_step" not in str(jaxpr)
    cfg = stride.StructuredConfig(net=net, shared_lnn=True)
    xla = models.make("stride", spec, act, cfg)
    fast = models.make("stride", spec, act, dataclasses.replace(cfg, kernel="pallas-step"))
    params = xla.init(jax.random.key(0))
    run = lambda m, p=params: jax.jit(jax.vmap(lambda *a: m.step(p, *a)))(q, qd, ctrl, keys)
    rounded_params = rounded(params)  # on a GPU the kernels' products run in TF32
    with exact():  # the float32 reference: tests/precision.py
        ref, moved = run(xla), run(xla, rounded_params)
    for name, r, o, m, s in zip(("q", "qd"), ref, run(fast), moved, (q, qd)):
        assert_close(o - s, r - s, sensitivity=jnp.max(jnp.abs(m - r)), floor=1e-6, err_msg=name)


def test_models_too_big_for_shared_memory_take_the_per_pass_kernels():
    """G1-sized (29 joints) at 128 wide exceeds an SM's shared memory as one kernel (measured
    on an H100): the step is traced with the per-pass kernels instead; Go1-sized fits at 256."""
    assert models.whole_step_fits(18, 256) and models.whole_step_fits(35, 64)
    assert not models.whole_step_fits(35, 128)
    spec, act = _robot(29)
    cfg = stride.StructuredConfig(net=mlp.MLPConfig(hidden=128, depth=1), shared_lnn=True,
                                  kernel="pallas-step")
    model = models.make("stride", spec, act, cfg)
    params = model.init(jax.random.key(0))
    q, qd, ctrl, keys = _states(spec, 4)
    jaxpr = str(jax.make_jaxpr(jax.vmap(lambda *a: model.step(params, *a)))(q, qd, ctrl, keys))
    assert "stride_fused_step" not in jaxpr and "stride_fused_mlp" in jaxpr


def test_program_rows_fill_the_gpu_before_halving():
    """8 rows where 16-row programs would leave multiprocessors idle and 8 rows add no wave
    (K = 1024 on an H200's 132 SMs: 128 programs, one wave), else 16 (K = 2048: 128 programs of
    16 are one wave, 256 of 8 would be two); 16 where the device reports no multiprocessors."""
    rows = fused_step.program_rows
    assert rows(1024, sms=132) == 8 and rows(256, sms=132) == 8 and rows(20, sms=132) == 8
    assert rows(2048, sms=132) == 16 and rows(4096, sms=132) == 16
    assert rows(1024, sms=64) == 16  # 128 programs of 8 would be two waves
    assert rows(1024, sms=0) == 16
