"""Recorded quantities against MuJoCo's own: equation of motion, contact forces, contact flags."""

import copy
import dataclasses

import jax
import mujoco
import numpy as np
import pytest

from stride_jax.sim import model, randomize, rollout_cpu, rollout_mjx


def _converged(sm):
    """The same robot with a converged constraint solve, so backends can be compared tightly."""
    mj = copy.copy(sm.mj)
    mj.opt.iterations, mj.opt.ls_iterations, mj.opt.tolerance = 100, 50, 1e-10
    return dataclasses.replace(sm, mj=mj)


def _episode_models(sm, ep):
    fields = randomize.nominal_fields(sm.mj)
    return [randomize.apply_mujoco(sm.mj, fields, jax.tree.map(lambda a: a[i], ep.rand),
                                   sm.base_body) for i in range(len(ep.valid))]


def _eom_residual(sm, models, ep):
    """max |M qdd - (tau + passive + constraint + external - bias)| / scale over valid steps."""
    r = ep.records
    worst, scale = 0.0, 1e-9
    for i, m in enumerate(models):
        d = mujoco.MjData(m)
        M = np.zeros((m.nv, m.nv))
        for t in np.flatnonzero(ep.valid[i]):
            d.qpos[:] = r.q[i, t]
            mujoco.mj_forward(m, d)
            mujoco.mj_fullM(m, d, M)
            rhs = (r.tau[i, t] + r.qfrc_passive[i, t] + r.qfrc_constraint[i, t]
                   + r.qfrc_external[i, t] - r.qfrc_bias[i, t])
            worst = max(worst, np.abs(M @ r.qdd[i, t] - rhs).max())
            scale = max(scale, np.abs(rhs).max())
    return worst / scale


@pytest.mark.parametrize("name", ["pendulum_bouncing", "go1", "g1"])
def test_cpu_records_satisfy_the_equation_of_motion(name):
    sm = model.load(name)
    ep = rollout_cpu.collect(sm, jax.random.key(3), 3, 60)
    assert ep.valid.any()
    assert np.abs(ep.records.qfrc_external).max() > 0 or name.startswith("pendulum")
    assert _eom_residual(sm, _episode_models(sm, ep), ep) < 1e-4  # float32 storage


@pytest.mark.slow  # MJX's whole collect program (35 s on 2 cores); fast: the CPU records' equation of motion
# above and test_mjx_forces_and_flags_match_mujoco (MJX's records against MuJoCo's on the same steps)
def test_mjx_records_satisfy_the_equation_of_motion(go1):
    ep = rollout_mjx.collect(go1, jax.random.key(4), 2, 60)
    assert _eom_residual(go1, _episode_models(go1, ep), ep) < 2e-3  # float32 simulation


@pytest.mark.parametrize("name", ["pendulum_bouncing", "go1"])
def test_mjx_forces_and_flags_match_mujoco(name):
    """MJX's per-foot normal forces (decoded from its constraint rows) equal mj_contactForce's."""
    sm = _converged(model.load(name))
    rng = np.random.default_rng(0)
    T = 40
    if sm.robot.floating_base:
        q0 = sm.info.qpos0.astype(np.float64)
        q0[2] += 0.01
        ctrl = np.clip(sm.info.qpos0[7:] + 0.15 * rng.standard_normal((T, sm.mj.nu)),
                       sm.info.ctrl_lo, sm.info.ctrl_hi)
    else:
        q0, ctrl = np.array([-0.2]), np.full((T, 1), -6.0)  # drive the bob into the wall
    qd0 = np.zeros(sm.mj.nv)
    mjx_rec = rollout_mjx.simulate(sm, q0, qd0, ctrl)
    cpu_rec = rollout_cpu.simulate(sm, q0, qd0, ctrl)
    if sm.nfeet:
        forces = cpu_rec.foot_force
        assert forces.max() > 1.0, "the test trajectory never touches"
        np.testing.assert_allclose(mjx_rec.foot_force, forces, atol=1e-3 * forces.max())
        np.testing.assert_array_equal(mjx_rec.foot_contact, cpu_rec.foot_contact)
    else:
        assert np.abs(cpu_rec.qfrc_constraint).max() > 1.0  # the wall pushed back
    np.testing.assert_allclose(mjx_rec.q, cpu_rec.q, atol=2e-3)
    np.testing.assert_allclose(mjx_rec.qfrc_constraint, cpu_rec.qfrc_constraint,
                               atol=2e-3 * np.abs(cpu_rec.qfrc_constraint).max())


@pytest.mark.slow  # the backends' trajectories and forces: test_mjx_forces_and_flags_match_mujoco
def test_backends_agree_on_a_short_trajectory_with_the_robots_own_solver(go1):
    """With the robot's few-iteration solver both backends still follow the same trajectory."""
    rng = np.random.default_rng(1)
    q0 = go1.info.qpos0.astype(np.float64)
    q0[2] += 0.02
    ctrl = np.clip(go1.info.qpos0[7:] + 0.1 * rng.standard_normal((15, go1.mj.nu)),
                   go1.info.ctrl_lo, go1.info.ctrl_hi)
    a = rollout_cpu.simulate(go1, q0, np.zeros(go1.mj.nv), ctrl)
    b = rollout_mjx.simulate(go1, q0, np.zeros(go1.mj.nv), ctrl)
    np.testing.assert_allclose(b.q, a.q, atol=5e-3)
    np.testing.assert_allclose(b.foot_force, a.foot_force, atol=0.05 * a.foot_force.max())


def test_contact_flags_follow_positive_normal_force(go1):
    ep = rollout_cpu.collect(go1, jax.random.key(5), 2, 40)
    r = ep.records
    np.testing.assert_array_equal(r.foot_contact, r.foot_force > 0)
    assert r.foot_contact[ep.valid].any() and (~r.foot_contact[ep.valid]).any()


@pytest.mark.parametrize("bad, match", [
    (dict(ctrl=np.full((5, 12), np.nan)), "ctrl contains NaN"),
    (dict(ctrl=np.zeros((5, 11))), r"ctrl has shape \[5, 11\], expected \[T >= 1, 12\]"),
    (dict(qpos=np.zeros(18)), r"qpos has shape \[18\], expected \[19\]"),
    (dict(qvel=np.full(18, np.inf)), "qvel contains NaN or inf"),
])
@pytest.mark.parametrize("backend", [rollout_cpu, rollout_mjx])
def test_bad_open_loop_inputs_are_clear_errors(go1, backend, bad, match):
    args = dict(qpos=go1.info.qpos0, qvel=np.zeros(18), ctrl=np.zeros((5, 12)))
    args.update(bad)
    with pytest.raises(ValueError, match=match):
        backend.simulate(go1, args["qpos"], args["qvel"], args["ctrl"])
