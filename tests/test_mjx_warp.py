"""MuJoCo Warp as a data backend: the same records as MuJoCo's, the same episodes as MJX's JAX
physics, and clear errors for what it cannot do. Runs where ``warp-lang`` is installed (its CPU
kernels here, CUDA on a GPU); skipped otherwise."""

import dataclasses

import jax
import numpy as np
import pytest

from stride_jax.robots.base import stochastic
from stride_jax.sim import model, mjx_warp, rollout_cpu, rollout_mjx

from test_record import _converged, _eom_residual, _episode_models

pytestmark = pytest.mark.skipif(not mjx_warp.installed(), reason="warp-lang is not installed")


def test_warp_forces_and_trajectory_match_mujoco(go1):
    """Open loop with a converged solver: Warp's per-foot forces, decoded through its constraint
    rows' contact ids, and its trajectory equal MuJoCo's."""
    sm = _converged(go1)
    rng = np.random.default_rng(0)
    T = 30
    q0 = sm.info.qpos0.astype(np.float64)
    q0[2] += 0.01
    ctrl = np.clip(sm.info.qpos0[7:] + 0.15 * rng.standard_normal((T, sm.mj.nu)),
                   sm.info.ctrl_lo, sm.info.ctrl_hi)
    w = rollout_mjx.simulate(sm, q0, np.zeros(sm.mj.nv), ctrl, impl="warp")
    c = rollout_cpu.simulate(sm, q0, np.zeros(sm.mj.nv), ctrl)
    assert c.foot_force.max() > 1.0, "the test trajectory never touches"
    assert (c.foot_force == 0).any(), "every foot stays down: flags untested"
    np.testing.assert_allclose(w.foot_force, c.foot_force, atol=1e-3 * c.foot_force.max())
    np.testing.assert_array_equal(w.foot_contact, c.foot_contact)
    np.testing.assert_allclose(w.q, c.q, atol=2e-3)
    np.testing.assert_allclose(w.qd, c.qd, atol=2e-3 * np.abs(c.qd).max())
    np.testing.assert_allclose(w.time, c.time, atol=1e-6)


@pytest.mark.slow  # MJX's equation-of-motion records: test_record.py
@pytest.mark.parametrize("name", ["go1", "g1"])
def test_warp_records_satisfy_the_equation_of_motion(name):
    sm = model.load(name)
    ep = rollout_mjx.collect(sm, jax.random.key(4), 2, 40, impl="warp")
    assert ep.valid.any()
    assert np.abs(ep.records.qfrc_external).max() > 0  # the pushes reach the records
    assert _eom_residual(sm, _episode_models(sm, ep), ep) < 2e-3  # float32 simulation


@pytest.mark.slow  # a trajectory: test_warp_forces_and_trajectory_match_mujoco
def test_warp_and_jax_physics_make_the_same_episodes(go1):
    """Same keys, same explorer, randomization and recording: the two physics part only by
    float32 round-off over a short episode."""
    a = rollout_mjx.collect(go1, jax.random.key(7), 3, 15)
    b = rollout_mjx.collect(go1, jax.random.key(7), 3, 15, impl="warp")
    jax.tree.map(np.testing.assert_array_equal, a.rand, b.rand)
    np.testing.assert_array_equal(a.records.ctrl[:, 0], b.records.ctrl[:, 0])
    np.testing.assert_allclose(b.records.q, a.records.q, atol=0.02)
    scale = np.abs(a.records.foot_force).max()
    assert scale > 1.0
    np.testing.assert_allclose(b.records.foot_force[:, :5], a.records.foot_force[:, :5],
                               atol=0.05 * scale)


@pytest.mark.slow  # Warp compiles slowly on a CPU
def test_warp_runs_ground_patches_and_refuses_rough_ground(go1):
    r = stochastic(go1.robot.randomization)
    patches = dataclasses.replace(go1, robot=dataclasses.replace(
        go1.robot, randomization=dataclasses.replace(r, rough_m=(0.0, 0.0))))
    ep = rollout_mjx.collect(patches, jax.random.key(2), 2, 20, impl="warp")
    assert ep.valid.any() and np.isfinite(ep.records.qdd[ep.valid]).all()
    rough = dataclasses.replace(go1, robot=dataclasses.replace(go1.robot, randomization=r))
    with pytest.raises(ValueError, match="heightfield"):
        rollout_mjx.collect(rough, jax.random.key(2), 2, 5, impl="warp")


def test_unknown_impl_is_a_clear_error(go1):
    with pytest.raises(ValueError, match="unknown MJX implementation 'torch'"):
        rollout_mjx.collect(go1, jax.random.key(0), 2, 5, impl="torch")


@pytest.mark.slow  # Warp compiles slowly on a CPU
def test_warp_on_several_devices_is_a_clear_error():
    """Warp runs one device per process; with two (forced host) devices it says so."""
    import os
    import subprocess
    import sys
    env = dict(os.environ, XLA_FLAGS=(os.environ.get("XLA_FLAGS", "") +
                                      " --xla_force_host_platform_device_count=2").strip())
    code = ("import jax; from stride_jax.sim import model, rollout_mjx\n"
            "rollout_mjx.collect(model.load('go1'), jax.random.key(0), 2, 2, impl='warp')")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         timeout=600)
    assert out.returncode != 0
    assert "one device per process and this process sees 2" in out.stderr
