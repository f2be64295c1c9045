"""The Euler-Lagrange machinery against MuJoCo: with MuJoCo's own mass matrix M(q) and potential
V(q) plugged in as the "networks", the autodiff bias C(q, qd) qd + g(q) must equal qfrc_bias."""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx

from stride_jax.dynamics import integrate, lagrangian
from stride_jax.sim import model


def _mujoco_energy(m: mujoco.MjModel):
    """MuJoCo's M(q) and gravitational V(q) as differentiable JAX functions (through MJX)."""
    mx = mjx.put_model(m)

    def kin(q):
        return mjx.kinematics(mx, mjx.make_data(mx).replace(qpos=q))

    def mass(q):
        d = mjx.crb(mx, mjx.com_pos(mx, kin(q)))
        return mjx.full_m(mx, d)

    def potential(q):
        return -jnp.sum(mx.body_mass * (kin(q).xipos @ mx.opt.gravity))

    return mass, potential


def _random_states(sm, rng, n):
    m = sm.mj
    for _ in range(n):
        q = sm.info.qpos0.astype(np.float64).copy()
        if sm.robot.floating_base:
            quat = rng.standard_normal(4)
            q[3:7] = quat / np.linalg.norm(quat)
            q[7:] += 0.3 * rng.standard_normal(m.nq - 7)
        else:
            q[:] = rng.uniform(-np.pi, np.pi, m.nq)
        yield q, 2.0 * rng.standard_normal(m.nv)


@pytest.mark.parametrize("name", ["pendulum", "go1"])
def test_autodiff_bias_reproduces_mujoco(name):
    sm = model.load(name)
    m = sm.mj
    d = mujoco.MjData(m)
    with jax.enable_x64(True):
        mass, potential = _mujoco_energy(m)
        terms = jax.jit(lambda q, v: lagrangian.bias_force(mass, potential, q, v,
                                                           sm.robot.floating_base))
        for q, v in _random_states(sm, np.random.default_rng(0), 5):
            d.qpos[:], d.qvel[:] = q, v
            mujoco.mj_forward(m, d)
            M_ref = np.zeros((m.nv, m.nv))
            mujoco.mj_fullM(m, d, M_ref)
            M, b = jax.device_get(terms(jnp.asarray(q), jnp.asarray(v)))
            np.testing.assert_allclose(M, M_ref, atol=1e-9)
            np.testing.assert_allclose(b, d.qfrc_bias, rtol=1e-7, atol=1e-7 * np.abs(d.qfrc_bias).max())


def test_the_rotation_term_matters():
    """Without the Euler-Poincare term omega x p the floating-base bias would be wrong."""
    sm = model.load("go1")
    m = sm.mj
    d = mujoco.MjData(m)
    q, v = next(_random_states(sm, np.random.default_rng(1), 1))
    d.qpos[:], d.qvel[:] = q, v
    mujoco.mj_forward(m, d)
    with jax.enable_x64(True):
        mass, potential = _mujoco_energy(m)
        terms = jax.jit(lambda q, v: lagrangian.bias_force(mass, potential, q, v, True))
        M, b_free = terms(jnp.asarray(q), jnp.asarray(v))
        # Treating the quaternion update as if omega were a coordinate rate drops omega x p:
        p = np.asarray(M) @ v
        wrong = np.asarray(b_free).copy()
        wrong[3:6] -= np.cross(v[3:6], p[3:6])
    assert np.abs(np.asarray(b_free) - d.qfrc_bias).max() < 1e-6
    assert np.abs(wrong - d.qfrc_bias).max() > 1e-2


def test_forward_dynamics_matches_mujoco_smooth_acceleration():
    """f_LNN with MuJoCo's M and V equals MuJoCo's unconstrained acceleration (pendulum)."""
    sm = model.load("pendulum")
    m = sm.mj
    d = mujoco.MjData(m)
    d.qpos[:], d.qvel[:], d.ctrl[:] = 1.0, -2.0, 0.7
    mujoco.mj_forward(m, d)
    with jax.enable_x64(True):
        mass, potential = _mujoco_energy(m)
        fd = jax.jit(lambda q, v, tau: lagrangian.forward_dynamics(mass, potential, q, v, tau,
                                                                   False))
        qdd = fd(jnp.array([1.0]), jnp.array([-2.0]), jnp.asarray(d.qfrc_actuator))
    # qacc_smooth also holds passive forces; remove their share to compare the rigid body part.
    M = np.zeros((1, 1))
    mujoco.mj_fullM(m, d, M)
    expected = d.qacc_smooth - np.linalg.solve(M, d.qfrc_passive)
    np.testing.assert_allclose(np.asarray(qdd), expected, rtol=1e-9)


def test_retract_matches_mujoco_integration():
    sm = model.load("go1")
    m = sm.mj
    rng = np.random.default_rng(2)
    q, v = next(_random_states(sm, rng, 1))
    ref = q.copy()
    mujoco.mj_integratePos(m, ref, v, 0.01)
    with jax.enable_x64(True):
        out = integrate.retract(jnp.asarray(q), jnp.asarray(0.01 * v), True)
    np.testing.assert_allclose(np.asarray(out), ref, atol=1e-12)
