import mujoco
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



@pytest.mark.parametrize("name", ["go1", "g1"])
def test_models_without_visual_meshes_simulate_the_same(name):
    import copy
    import numpy as np
    lean, full = model.load(name), model.compile_robot(robots.get(name), visual=True)
    assert lean.mj.nmesh == 0 and lean.mj.ntex == 0 and full.mj.nmesh > 0
    np.testing.assert_array_equal(lean.mj.body_mass, full.mj.body_mass)
    np.testing.assert_array_equal(lean.mj.body_inertia, full.mj.body_inertia)
    qs = []
    for m in (lean.mj, full.mj):
        d = mujoco.MjData(m)
        d.qpos[:] = lean.info.qpos0
        d.qpos[2] += 0.02
        for _ in range(60):
            d.ctrl[:] = lean.info.qpos0[7:]
            mujoco.mj_step(m, d)
        qs.append(d.qpos.copy())
        assert d.ncon > 0  # standing on its feet
    np.testing.assert_array_equal(qs[0], qs[1])
    assert copy.copy(lean.mj).nbuffer < full.mj.nbuffer / 50
