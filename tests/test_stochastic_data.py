"""Data with a stochastic contact residual: ground patches under each foot, several pushes, and
walking data from a trained policy. Reproducible from the seed, hidden from the models' inputs."""

import dataclasses

import jax
import mujoco
import numpy as np
import pytest

from stride_jax.robots import stochastic
from stride_jax.jobs import data as collect
from stride_jax.sim import dataset, model, randomize, rollout_cpu, rollout_mjx
from stride_jax.train import dynamics as train_dynamics


@pytest.fixture(scope="module")
def go1():
    return model.load("go1")


@pytest.fixture(scope="module")
def go1_stochastic(go1):
    r = stochastic(go1.robot.randomization)
    return dataclasses.replace(go1, robot=dataclasses.replace(go1.robot, randomization=r))


def _standing_contacts(m, sm):
    d = mujoco.MjData(m)
    d.qpos[:] = sm.info.qpos0
    d.qpos[2] -= 0.01  # feet pressed into the floor: four contacts
    mujoco.mj_forward(m, d)
    c = d.contact[:d.ncon]
    foot = sm.geom_foot[np.where(sm.geom_foot[c.geom1] >= 0, c.geom1, c.geom2)]
    return foot, c.friction.copy(), c.solref.copy(), c.solimp.copy()


def test_ground_ready_model_has_the_same_contacts(go1):
    ready = randomize.ground_ready(go1.mj, go1.geom_foot)
    foot0, *before = _standing_contacts(go1.mj, go1)
    foot1, *after = _standing_contacts(ready, go1)
    assert len(foot0) == 4 and (foot0 == foot1).all()
    for a, b in zip(before, after):
        np.testing.assert_allclose(a, b, rtol=1e-12)
    assert (ready.geom_priority[go1.foot_geoms[:, 0]] > 0).all()


@pytest.mark.parametrize("name", ["go1", "g1"])  # geom-geom contacts; explicit contact pairs
def test_a_patch_scales_only_its_own_foot(name):
    sm = model.load(name)
    ready = randomize.ground_ready(sm.mj, sm.geom_foot)
    base = randomize.nominal_fields(ready)
    pair_foot = randomize.pair_feet(ready, sm.geom_foot)
    fric, soft = np.ones(sm.nfeet), np.ones(sm.nfeet)
    fric[0], soft[-1] = 0.3, 2.0  # the first foot on slippery ground, the last on soft ground
    edited = randomize.apply_mujoco(ready, base, randomize.sample(
        jax.random.key(0), dataclasses.replace(sm.robot.randomization, friction=(1, 1),
                                               softness=(1, 1), payload_kg=(0, 0)), 5.0),
        sm.base_body)
    for k, a in randomize.apply_ground(base, sm.geom_foot, pair_foot, fric, soft, np).items():
        getattr(edited, k)[...] = a
    foot, f0, r0, _ = _standing_contacts(ready, sm)
    foot1, f1, r1, _ = _standing_contacts(edited, sm)
    assert (foot == foot1).all() and len(set(foot.tolist())) == sm.nfeet
    np.testing.assert_allclose(f1[:, 0], f0[:, 0] * fric[foot], rtol=1e-9)
    np.testing.assert_allclose(r1[:, 0], r0[:, 0] * soft[foot], rtol=1e-9)


def test_new_draws_leave_the_old_ones_unchanged(go1):
    r = go1.robot.randomization
    key = jax.random.key(3)
    old, new = randomize.sample(key, r, 10.0), randomize.sample(key, stochastic(r), 10.0)
    for f in ("friction", "softness", "payload_kg", "damping", "push_t", "push_s", "push_force"):
        np.testing.assert_array_equal(getattr(old, f), getattr(new, f))
    assert old.extra_push_t.shape == (0,) and new.extra_push_t.shape == (2,)


def test_patches_are_a_function_of_place(go1_stochastic):
    r = go1_stochastic.robot.randomization
    v = randomize.sample(jax.random.key(5), r, 10.0)
    xy = np.array([[0.01, 0.02], [0.25, 0.1], [0.35, 0.1], [-0.2, -5.0]], np.float32)
    f, s = randomize.foot_patches(v, r, xy)
    f2, s2 = randomize.foot_patches(v, r, xy + 0.01)  # same squares
    np.testing.assert_array_equal(f, f2)
    np.testing.assert_array_equal(s, s2)
    assert f[0] == f[1] and f[1] != f[2]  # 0.3 m squares: the third point is in the next one
    lo, hi = r.patch_friction
    assert ((np.asarray(f) >= lo) & (np.asarray(f) <= hi)).all()
    other = randomize.sample(jax.random.key(6), r, 10.0)
    assert not np.array_equal(f, randomize.foot_patches(other, r, xy)[0])


def test_several_pushes_act(go1_stochastic):
    r = go1_stochastic.robot.randomization
    v = randomize.sample(jax.random.key(7), r, 10.0)
    for t in [float(v.push_t)] + [float(x) for x in v.extra_push_t]:
        d = randomize.disturbance(v, r, t + 1e-3, np.zeros(19, np.float32), 18)
        assert np.linalg.norm(d.push) > 0


def test_stochastic_data_is_reproducible(go1_stochastic):
    key = jax.random.key(11)
    a = rollout_cpu.collect(go1_stochastic, key, 3, 40)
    b = rollout_cpu.collect(go1_stochastic, key, 3, 40)
    np.testing.assert_array_equal(a.records.q, b.records.q)
    c = rollout_cpu.collect(go1_stochastic, jax.random.key(12), 3, 40)
    assert not np.allclose(a.records.q, c.records.q)


@pytest.mark.slow  # MJX against MuJoCo on flat ground: test_record.py::test_mjx_forces_and_flags_match_mujoco
def test_stochastic_data_backends_agree(go1_stochastic):
    key = jax.random.key(11)
    # Same worlds, patches and pushes: the trajectories stay close over 0.8 s (float32 MJX). On
    # flat ground only: on rough ground (a heightfield) MuJoCo's collider gives a foot one
    # contact per prism it touches, MJX four manifold points with the top faces' normals, and
    # the backends part within a few steps (tests/test_rough_ground.py checks each on its own).
    r = go1_stochastic.robot.randomization
    assert r.rough
    flat = dataclasses.replace(go1_stochastic, robot=dataclasses.replace(
        go1_stochastic.robot, randomization=dataclasses.replace(r, rough_m=(0.0, 0.0))))
    a = rollout_cpu.collect(flat, key, 3, 40)
    m = rollout_mjx.collect(flat, key, 3, 40)
    err = np.abs(m.records.q[:, :20] - a.records.q[:, :20]).max()
    assert err < 0.05, err


def test_hidden_values_do_not_reach_the_training_examples(tmp_path):
    cfg = collect.DataConfig(robot="go1", backend="cpu", episodes=3, seconds=0.6, stochastic=True,
                             out=str(tmp_path / "d"))
    ds = collect.generate(cfg)
    assert ds.meta["randomization"]["patch_m"] > 0 and ds.meta["randomization"]["pushes"] == 3
    split = ds.split("train")
    ex = train_dynamics.examples(split)
    altered = {k: (np.random.default_rng(0).permutation(v) if k.startswith("rand/") else v)
               for k, v in split.items()}
    for k, v in train_dynamics.examples(altered).items():
        np.testing.assert_array_equal(v, ex[k])
    assert not any(k.startswith(("rand", "explore")) for k in ex)
    assert isinstance(dataset.load(ds.path), dataset.Dataset)


def test_walking_explorer_tracks_its_commands(tmp_path):
    from stride_jax.control import walk
    explorer = walk.PolicyExplorer("results/policies/ppo_go1", action_noise=0.0)
    cfg = collect.DataConfig(robot="go1", backend="cpu", episodes=4, seconds=3.0,
                             policy="results/policies/ppo_go1", action_noise=0.0,
                             out=str(tmp_path / "w"))
    ds = collect.generate(cfg, explorer)
    a = ds.arrays
    from stride_jax.control import envs
    v = jax.vmap(jax.vmap(lambda q, qd: envs.base_signals(q, qd)[0]))(a["q"], a["qd"])
    speed = np.asarray(v[:, 50:, :2]).mean(1)
    cmd = a["explore/commands"][:, 0, :2]
    assert np.abs(speed - cmd).max() < 0.3, (speed, cmd)
    assert ds.meta["explorer"].startswith("PolicyExplorer")
    with pytest.raises(ValueError, match="pass its explorer"):
        collect.generate(cfg)
