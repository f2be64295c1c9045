"""Rough ground: a heightfield drawn per episode, in both backends, with records that keep the
equation of motion and foot forces that carry the robot."""

import dataclasses
import pathlib
import sys

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx

from stride_jax.robots import Randomization, stochastic
from stride_jax.sim import model, record, rollout_cpu, rollout_mjx, terrain

sys.path.insert(0, str(pathlib.Path(__file__).parent))
from test_record import _eom_residual  # noqa: E402

ROUGH = dict(rough_m=(0.03, 0.03), rough_scale_m=(0.2, 0.5))


def _rough(name, **kw):
    sm = model.load(name)
    r = dataclasses.replace(stochastic(sm.robot.randomization), **(ROUGH | kw))
    return dataclasses.replace(sm, robot=dataclasses.replace(sm.robot, randomization=r)), r


def test_stochastic_turns_rough_ground_on_and_nothing_else_does():
    base = model.load("go1").robot.randomization
    assert not base.rough and stochastic(base).rough
    assert stochastic(base).rough_m == (0.0, 0.03)
    sm = model.load("go1")
    assert terrain.rough_model(sm, base) is sm and sm.mj.nhfield == 0
    # off: the flat floor and the records' old foot-force path (data byte-identical to before)
    assert record.mjx_contact_layout(sm, mjx.put_model(sm.mj)).sign is None
    assert terrain.rough_model(sm, stochastic(base)).mj.nhfield == 1
    with pytest.raises(ValueError, match="rough_m"):
        Randomization(rough_m=(0.02, 0.01))
    with pytest.raises(ValueError, match="rough_cell_m"):
        Randomization(rough_m=(0.0, 0.01), rough_cell_m=0.0)


def test_heights_differ_between_episodes_and_start_below_the_feet():
    _, r = _rough("go1")
    seeds = jax.random.bits(jax.random.key(0), (3,), jnp.uint32)
    grids = np.asarray(jax.vmap(lambda s: terrain.height_grid(s, r))(seeds))
    assert grids.shape == (3, terrain.grid_size(r), terrain.grid_size(r))
    assert not np.allclose(grids[0], grids[1]) and not np.allclose(grids[1], grids[2])
    x, y = terrain.grid_points(r)
    near = (x[None, :] ** 2 + y[:, None] ** 2) <= terrain.START_RADIUS ** 2
    for g in grids:
        assert g[near].max() == pytest.approx(0.0, abs=1e-6)  # the start lies at the floor's level
        assert g.std() > 0.003 and g.max() - g.min() <= 4 * r.rough_m[1] + 1e-6
        # smooth: neighbouring samples 5 cm apart differ far less than the field's spread
        assert np.abs(np.diff(g, axis=1)).mean() < 0.5 * g.std()
    np.testing.assert_array_equal(grids[0], terrain.height_grid(seeds[0], r))  # from the seed


@pytest.mark.parametrize("name", ["go1", pytest.param("g1", marks=pytest.mark.slow)])  # G1's pairs
# on rough ground in `make test`: test_control_closed_loop.py::test_rough_ground_takes_the_floors_contact_pairs
def test_a_bump_under_one_foot_lifts_that_foot_in_both_backends(name):
    """The same pose over flat ground (every foot clear by 5 mm) and over a bump of 2 cm under the
    first foot only: only that foot touches, in MuJoCo and in MJX (per-world heights)."""
    sm, r = _rough(name)
    rs = terrain.rough_model(sm, r)
    m = rs.mj
    d = mujoco.MjData(m)
    d.qpos[:] = sm.info.qpos0
    mujoco.mj_kinematics(m, d)
    # lowest point of a sphere or capsule: centre - radius - half-length * |axis_z|
    low = [min(d.geom_xpos[g, 2] - m.geom_size[g, 0] - (
        m.geom_size[g, 1] * abs(d.geom_xmat[g, 8])
        if m.geom_type[g] == mujoco.mjtGeom.mjGEOM_CAPSULE else 0.0) for g in geoms[geoms >= 0]) for geoms in rs.foot_geoms]
    d.qpos[2] += 0.005 - min(low)  # the lowest foot 5 mm above z = 0
    x, y = terrain.grid_points(r)
    flat = np.zeros((len(y), len(x)), np.float32)
    mujoco.mj_kinematics(m, d)
    fx, fy = d.site_xpos[rs.foot_sites[0], :2]
    bump = flat + 0.02 * np.exp(-((x[None, :] - fx) ** 2 + (y[:, None] - fy) ** 2) / 0.06 ** 2)
    forces = {}
    for label, h in (("flat", flat), ("bump", bump)):
        data = np.asarray(terrain.to_data(jnp.asarray(h), r)).reshape(-1)
        m.hfield_data[:] = data
        i, j = (int((v + r.rough_extent_m) // r.rough_cell_m) for v in (fy, fx))
        corners = h[i:i + 2, j:j + 2]  # MuJoCo's surface interpolates the four samples around
        assert corners.min() - 1e-4 <= terrain.ground_height(m, (fx, fy)) <= corners.max() + 1e-4
        mujoco.mj_forward(m, d)
        cpu = record.from_mujoco(rs, m, d)
        mx = mjx.put_model(m).replace(hfield_data=jnp.asarray(data, jnp.float32))
        qpos = jnp.asarray(d.qpos, jnp.float32)
        dx = jax.jit(mjx.forward)(mx, mjx.make_data(mx).replace(qpos=qpos))
        gpu = record.from_mjx(rs, dx, record.mjx_contact_layout(rs, mx), mx.opt.gravity)
        forces[label] = (cpu.foot_contact, np.asarray(gpu.foot_contact))
    for contact in forces["flat"]:
        assert not contact.any()
    for contact in forces["bump"]:
        assert contact[0] and not contact[1:].any()


@pytest.fixture(scope="module")
def go1_rough():
    return _rough("go1")


@pytest.mark.parametrize("backend", ["cpu", pytest.param("mjx", marks=pytest.mark.slow)])  # MJX on
# a heightfield in `make test`: test_a_bump_under_one_foot_lifts_that_foot_in_both_backends[go1]
def test_rough_records_satisfy_the_equation_of_motion_and_carry_the_robot(go1_rough, backend):
    sm, r = go1_rough
    rs = terrain.rough_model(sm, r)
    mod = rollout_cpu if backend == "cpu" else rollout_mjx
    ep = mod.collect(sm, jax.random.key(3), 2, 30)
    assert ep.valid[:, :20].all()
    models, _ = rollout_cpu.randomized_worlds(rs, r, ep.rand)
    assert not np.array_equal(models[0].hfield_data, models[1].hfield_data)  # worlds differ
    assert _eom_residual(rs, models, ep) < (1e-4 if backend == "cpu" else 2e-3)
    # The feet carry the robot: over 0.6 s the vertical contact forces average to about its
    # weight (the pushes are horizontal). A sum of the heightfield contacts' normal forces
    # would not (up to 6 kN per foot where a foot sinks into soft ground between prisms).
    weight = np.array([m.body_mass.sum() * 9.81 for m in models])  # payloads included
    load = ep.records.foot_force.sum(-1).mean(-1)
    assert (np.abs(load / weight - 1) < 0.35).all(), load / weight
    assert ep.records.foot_force.max() < 10 * weight.max()
