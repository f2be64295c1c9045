"""Effects library: nominal round trip, and each effect moves the dynamics the expected way."""

import numpy as np
import pytest

from stride_jax.gap import effects, real, sim
from stride_jax.sim import model

MODEL_FIELDS = ("dof_damping", "dof_frictionloss", "dof_armature", "actuator_gainprm", "actuator_biasprm",
                "actuator_forcerange", "actuator_forcelimited", "geom_friction", "geom_solref",
                "body_mass", "body_inertia", "body_ipos", "jnt_stiffness", "qpos_spring")


@pytest.fixture(scope="module")
def pend():
    return model.load("pendulum")


@pytest.mark.parametrize("robot", ["pendulum", "go1"])
def test_nominal_values_reproduce_the_nominal_model(robot):
    sm = model.load(robot)
    clean, _ = real.generate(sm, None, 2, 15, seed=3, min_steps=3)
    q = np.concatenate([t.q for t in clean])
    qd = np.concatenate([t.qd for t in clean])
    u = np.concatenate([t.cmd for t in clean])
    b = np.cumsum([0] + [len(t.t) for t in clean])
    ref = sim.one_step(sm, effects.build(sm), q, qd, u, b)[1]
    everything = {e.name: np.asarray(e.nominal) for e in effects.ALL.values() if e.applies(sm)}
    for applied in [{n: p} for n, p in everything.items()] + [everything]:
        plan = effects.build(sm, applied)
        for f in MODEL_FIELDS:
            np.testing.assert_array_equal(getattr(plan.mj, f), getattr(sm.mj, f), err_msg=f"{applied} {f}")
        np.testing.assert_array_equal(sim.one_step(sm, plan, q, qd, u, b)[1], ref, err_msg=str(applied))
    # the logged states replay exactly in the model that produced them
    np.testing.assert_array_equal(ref, np.concatenate([t.qd[1:] for t in clean]))


def test_build_rejects_bad_requests(pend):
    with pytest.raises(KeyError, match="unknown effect"):
        effects.build(pend, {"gravity": 1.0})
    with pytest.raises(ValueError, match="3 parameter"):
        effects.build(pend, {"com_offset": 0.1})
    with pytest.raises(ValueError, match="does not apply"):
        effects.build(pend, {"kp_scale": 1.2})


def _acc(sm, applied, q, qd, u, first=None):
    """Mean acceleration over one control period from single states, under per-step commands."""
    plan = effects.build(sm, applied)
    cmd = np.asarray(u, float)
    start = np.array([len(cmd) - 1])
    _, v = sim.k_step(sm, plan, np.repeat(q[None], len(cmd), 0), np.repeat(qd[None], len(cmd), 0), cmd,
                      start, np.zeros(1, int), 1)
    return (v[0] - qd) / sm.robot.ctrl_dt


def test_pendulum_effects_move_the_dynamics_the_expected_way(pend):
    down, side = np.array([0.0]), np.array([np.pi / 2])
    spin, still = np.array([3.0]), np.array([0.0])
    push = [[4.0]]
    a = lambda applied, q=down, qd=still, u=push: _acc(pend, applied, q, qd, u)[0]
    # damping and dry friction brake a swinging pendulum
    assert a({"damping": 0.5}, qd=spin, u=[[0.0]]) < a({}, qd=spin, u=[[0.0]]) < 0
    assert a({"frictionloss": 0.5}, qd=spin, u=[[0.0]]) < a({}, qd=spin, u=[[0.0]])
    # armature and payload make a torque accelerate it less; a weaker motor too
    for applied in ({"armature": 0.2}, {"payload": 0.4}, {"torque_scale": 0.6}):
        assert 0 < a(applied) < a({}), applied
    assert a({"torque_limit": 0.5}, u=[[6.0]]) < a({}, u=[[6.0]])
    # a dead band swallows torques below it
    assert a({"deadzone": 1.0}, u=[[0.5]]) == pytest.approx(a({}, u=[[0.0]]))
    # moving the centre of mass towards the hinge shortens the pendulum: it falls faster (g / l)
    assert abs(a({"com_offset": [0, 0, 0.2]}, q=side, u=[[0.0]])) > abs(a({}, q=side, u=[[0.0]]))
    # a delay of one step applies the previous command
    assert a({"delay": 1}, u=[[0.0], [4.0]]) == pytest.approx(a({}, u=[[0.0]]))
    assert a({"delay": 1}, u=[[0.0], [4.0]]) < a({}, u=[[0.0], [4.0]])
    # out of library: a spring pulls to the home angle, drag brakes
    assert a({"joint_stiffness": 5.0}, q=side, u=[[0.0]]) < a({}, q=side, u=[[0.0]])
    assert a({"quadratic_drag": 0.2}, qd=spin, u=[[0.0]]) < a({}, qd=spin, u=[[0.0]])


def test_go1_effects_move_the_dynamics_the_expected_way(go1):
    home = np.asarray(go1.info.qpos0, float)
    zero = np.zeros(go1.mj.nv)
    cmd = home[7:].copy()
    # in the air: one joint commanded 0.3 rad away, a stiffer servo pulls harder
    air = home.copy()
    air[2] = 1.0
    u = cmd.copy()
    u[1] += 0.3
    acc = lambda applied, q=air, qd=zero, uu=u: _acc(go1, applied, q, qd, [uu])
    assert acc({"kp_scale": 1.5})[7] > acc({})[7] > acc({"kp_scale": 0.6})[7] > 0
    # standing (home leaves the feet inside the floor): softer contacts push the body up less
    assert acc({"contact_softness": 3.0}, q=home, uu=cmd)[2] < acc({}, q=home, uu=cmd)[2]
    # sliding sideways on the floor: less friction, less braking
    slide = zero.copy()
    slide[1] = 1.0
    q = home.copy()
    q[2] -= 0.005
    brake = lambda applied: -acc(applied, q=q, qd=slide, uu=cmd)[1]
    assert brake({"ground_friction": 0.3}) < brake({})
    # a payload pulls a free-falling robot no differently, but loads the servos in stance: it
    # sinks faster on its legs
    assert acc({"payload": 3.0}, q=home, uu=cmd)[2] < acc({}, q=home, uu=cmd)[2]


def test_replays_use_the_sparse_jacobian_on_a_floating_base_with_the_same_dynamics(pend):
    import mujoco

    go1 = model.load("go1")
    fast = sim.for_replay(go1)
    assert fast.mj.opt.jacobian == mujoco.mjtJacobian.mjJAC_SPARSE
    assert go1.mj.opt.jacobian != mujoco.mjtJacobian.mjJAC_SPARSE  # the caller's model is left alone
    assert sim.for_replay(pend) is pend  # no floating base: the model's own choice stands
    clean, _ = real.generate(go1, None, 2, 15, seed=3, min_steps=3)
    q, qd, u = (np.concatenate([getattr(t, f) for t in clean]) for f in ("q", "qd", "cmd"))
    b = np.cumsum([0] + [len(t.t) for t in clean])
    dense = sim.one_step(go1, effects.build(go1, {"damping": 0.5}), q, qd, u, b)[1]
    sparse = sim.one_step(fast, effects.build(fast, {"damping": 0.5}), q, qd, u, b)[1]
    np.testing.assert_allclose(sparse, dense, rtol=0, atol=1e-8)
