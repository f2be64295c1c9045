import mujoco
import numpy as np
import pytest

from stride_jax import robots
from stride_jax.sim import model


@pytest.mark.parametrize("name", ["pendulum", "pendulum_bouncing", "go1", "g1"])
def test_robot_compiles_with_named_parts(name):
    sm = model.load(name)
    assert sm.mj.nu == len(sm.robot.joints)
    assert sm.n_substeps * sm.mj.opt.timestep == pytest.approx(sm.robot.ctrl_dt)
    assert len(sm.foot_geoms) == len(sm.robot.feet)
    assert all((g >= 0).any() for g in sm.foot_geoms)
    assert sm.mj.opt.cone == mujoco.mjtCone.mjCONE_PYRAMIDAL


def test_go1_collides_only_at_the_feet(go1):
    m = go1.mj
    colliding = [m.geom(i).name for i in range(m.ngeom) if m.geom_contype[i] or m.geom_conaffinity[i]]
    assert sorted(colliding) == ["FL", "FR", "RL", "RR", "floor"]


def test_g1_keeps_only_foot_floor_pairs(g1):
    names = [g1.mj.pair(i).name for i in range(g1.mj.npair)]
    assert len(names) == 6 and all("foot" in n and n.endswith("_floor") for n in names)


def test_unknown_robot_is_a_clear_error():
    with pytest.raises(robots.RobotError, match="unknown robot 'go2'.*go1"):
        robots.get("go2")


@pytest.mark.parametrize("name", ["go1", "g1"])
def test_missing_menagerie_names_the_variable_and_robot(name, tmp_path, monkeypatch):
    monkeypatch.setenv("MENAGERIE_ROOT", str(tmp_path))  # an empty folder
    with pytest.raises(robots.RobotError, match=f"robot '{name}' needs .*MENAGERIE_ROOT"):
        model.compile_robot(robots.get(name))


def test_foot_dofs_are_the_chains_from_feet_to_world(go1, g1):
    legs = go1.foot_dofs()
    assert legs.shape == (4, go1.mj.nv)
    assert legs[:, :6].all()  # every foot pushes on the floating base
    assert (legs[:, 6:].sum(0) == 1).all()  # each joint belongs to exactly one leg
    assert (legs.sum(1) == 6 + 3).all()
    feet = g1.foot_dofs()
    arms = [g1.mj.joint(f"{s}_shoulder_pitch_joint").dofadr[0] for s in ("left", "right")]
    assert not feet[:, arms].any()  # the feet never act on the arms
    assert (feet[0] & feet[1]).sum() == 6  # the two legs share only the base


def test_training_examples_mark_only_dofs_a_stance_foot_reaches(go1):
    from stride_jax.train import loop

    nv = go1.mj.nv
    contact = np.zeros((1, 3, 4), bool)
    contact[0, 0, 0] = True  # step 0: one foot down; step 1: airborne
    split = {k: np.zeros((1, 3, n), np.float32) for k, n in
             (("q", go1.mj.nq), ("qd", nv), ("tau", nv), ("qdd", nv), ("ctrl", go1.mj.nu))}
    split.update(valid=np.ones((1, 3), bool), foot_contact=contact)
    ex = loop._examples(split, go1.foot_dofs())
    assert (ex["contact_dofs"][0] == go1.foot_dofs()[0]).all()
    assert not ex["contact_dofs"][1].any()
    with pytest.raises(loop.TrainingError, match="foot_dofs has shape"):
        loop._examples(split, go1.foot_dofs()[:2])
