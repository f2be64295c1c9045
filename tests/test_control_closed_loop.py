"""Closed-loop MPPI: a few jitted steps with the oracle (the true MJX dynamics) planning gait
parameters; scenario grounds; the planner state; gait parameters held per rollout; learned costs."""

import dataclasses
import json
import shutil

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from mujoco import mjx

from stride_jax.control import envs, gait, learned, mppi, scenarios
from stride_jax.control import planning as planning_lib
from stride_jax.jobs import closed_loop as cl


@pytest.mark.slow  # planning through MJX: test_mppi.py::test_bench_oracle_row_plans_through_mjx; the
# planner's gait: test_gait_parameters_are_held_per_rollout; episodes' rows and traces: the job's tests below
def test_oracle_closed_loop_runs_jitted_and_deterministically(go1):
    cfg = dataclasses.replace(cl.PRESETS["tiny"], planning=planning_lib.PlanningConfig(
        gait=True, noise_std=0.05))
    sc = cl.SCENARIOS["walk"]
    mx = mjx.put_model(cl.scenario_model(go1, sc))
    planning = planning_lib.make_planning(cfg.planning, envs.config("go1"), go1,
                                          cl.mjx_step_fn(go1, mx))
    planner = planning_lib.make_planner(planning, planning_lib.mppi_config(cfg.mppi, cfg.planning,
                                                                           planning))
    starts, values = cl.schedule(sc)
    n = 6
    episode = jax.jit(lambda key: cl.run_episode(go1, mx, envs.contact_slots(mx), planning,
                                                 planner, n, starts, values, key))
    key = jax.random.key(0)
    # XLA's backend optimisations cost a third of the compile time and buy nothing in 6 steps.
    episode = episode.lower(key).compile({"xla_backend_optimization_level": 0})
    trace = episode(key)
    again = episode(key)
    assert trace.v_base.shape == (n, 3) and trace.action.shape == (n, 12 + gait.N_GAIT)
    assert trace.contact.shape == (n, 4)
    np.testing.assert_allclose(trace.t, 0.02 * np.arange(1, n + 1), rtol=1e-6)
    np.testing.assert_array_equal(trace.command, np.tile([1.0, 0.0, 0.0], (n, 1)))
    assert np.isfinite(trace.v_base).all() and not trace.fallen.any()
    for a, b in zip(jax.tree.leaves(trace), jax.tree.leaves(again)):
        np.testing.assert_array_equal(a, b)
    # The planner's gait parameters stay in their bounds and the duty is a fraction.
    lo, hi = planning.lo, planning.hi
    assert (np.asarray(trace.action) >= lo - 1e-6).all()
    assert (np.asarray(trace.action) <= hi + 1e-6).all()
    m = cl.metrics(trace, settle_s=0.0)
    assert np.isfinite(m["vel_rmse"]) and m["fell"] is False and "plan_gait" in m


def test_scenario_grounds(go1):
    slope = cl.scenario_model(go1, cl.SCENARIOS["slope"])
    g = np.asarray(slope.opt.gravity)
    np.testing.assert_allclose(np.linalg.norm(g), 9.81, rtol=1e-6)
    np.testing.assert_allclose(np.degrees(np.arctan2(-g[0], -g[2])), 20.0, rtol=1e-6)
    ice = cl.scenario_model(go1, cl.SCENARIOS["low_friction"])
    np.testing.assert_allclose(ice.geom_friction[:, 0], 0.3 * go1.mj.geom_friction[:, 0])
    soft = cl.scenario_model(go1, cl.SCENARIOS["soft"])
    assert (soft.geom_solref[:, 0] > go1.mj.geom_solref[:, 0]).all()
    rough = cl.scenario_model(go1, cl.SCENARIOS["rough"])
    assert rough.nhfield == 1 and np.ptp(rough.hfield_data) > 0.5
    np.testing.assert_array_equal(go1.mj.opt.gravity, [0, 0, -9.81])  # nominal untouched
    # the payload: a quarter of the robot's mass on its base, inertia alike, centre kept
    load = cl.scenario_model(go1, cl.SCENARIOS["payload"])
    b, total = go1.base_body, go1.mj.body_mass.sum()
    np.testing.assert_allclose(load.body_mass.sum(), 1.25 * total, rtol=1e-9)
    np.testing.assert_allclose(load.body_subtreemass[0], 1.25 * total, rtol=1e-9)
    ratio = load.body_mass[b] / go1.mj.body_mass[b]
    np.testing.assert_allclose(load.body_inertia[b], ratio * go1.mj.body_inertia[b], rtol=1e-9)
    np.testing.assert_array_equal(load.body_ipos, go1.mj.body_ipos)
    d = mujoco.MjData(load)
    mujoco.mj_forward(load, d)  # gravity on the free joint's vertical: the loaded robot's weight
    np.testing.assert_allclose(d.qfrc_bias[2], 1.25 * total * 9.81, rtol=1e-6)
    assert go1.mj.body_mass.sum() == total  # nominal untouched
    with pytest.raises(ValueError, match="payload"):
        cl.Scenario("bad", cl.WALK, payload=-0.1)
    # carried by another body, named: that body takes it, the base nothing
    thigh = mujoco.mj_name2id(go1.mj, mujoco.mjtObj.mjOBJ_BODY, "FR_thigh")
    strapped = cl.scenario_model(go1, cl.Scenario("thigh", cl.WALK, payload=0.25, payload_body="FR_thigh"))
    np.testing.assert_allclose(strapped.body_mass[thigh] - go1.mj.body_mass[thigh], 0.25 * total, rtol=1e-9)
    assert strapped.body_mass[b] == go1.mj.body_mass[b]
    d = mujoco.MjData(strapped)
    mujoco.mj_forward(strapped, d)
    np.testing.assert_allclose(d.qfrc_bias[2], 1.25 * total * 9.81, rtol=1e-6)
    with pytest.raises(ValueError, match="'backpack' is not a body of 'go1'; its bodies: trunk"):
        cl.scenario_model(go1, cl.Scenario("bad", cl.WALK, payload=0.25, payload_body="backpack"))
    with pytest.raises(ValueError, match="payload of 0"):
        cl.Scenario("bad", cl.WALK, payload_body="trunk")
    starts, values = cl.schedule(cl.SCENARIOS["step"])
    np.testing.assert_allclose(cl.command_at(starts, values, 0.5), [0, 0, 0])
    np.testing.assert_allclose(cl.command_at(starts, values, 1.5), [2, 0, 0])
    with pytest.raises(ValueError, match="unknown model"):
        cl._parse_models("oracle,bogus")
    with pytest.raises(ValueError, match="unknown kernel 'triton'"):
        cl.run(cl.ClosedLoopConfig(kernel="triton"))


def test_scenario_world_is_the_scenario_as_the_closed_loop_runs_it(go1):
    """One call gives what an episode in a scenario needs: the scenario's ground in MJX, the
    robot on that model (its own geom ids), the feet's contact slots and the schedules."""
    from stride_jax.sim import model as sim_model
    sc = dataclasses.replace(cl.SCENARIOS["rough"], seconds=0.5, slope_deg=10.0, tilt_s=1.0,
                             pushes=((0.1, 0.2, 0.5, 0.0),))
    w = cl.scenario_world(go1, sc, seed=3)
    m = cl.scenario_model(go1, sc, 3)
    assert w.n_steps == 25  # 0.5 s of 20 ms periods
    np.testing.assert_array_equal(np.asarray(w.mx.hfield_data), m.hfield_data)  # seed 3's draw
    assert not np.array_equal(np.asarray(cl.scenario_world(go1, sc).mx.hfield_data),
                              m.hfield_data)
    np.testing.assert_array_equal(w.sm.geom_foot, sim_model.on_model(go1, m).geom_foot)
    for a, b in zip(w.slots, envs.contact_slots(w.mx)):
        np.testing.assert_array_equal(a, b)
    starts, values = cl.schedule(sc)
    np.testing.assert_array_equal(w.starts, starts)
    np.testing.assert_array_equal(w.values, values)
    np.testing.assert_allclose(w.pushes, cl.push_schedule(sc, float(go1.mj.body_mass.sum())))
    np.testing.assert_allclose(w.tilt, [np.deg2rad(10.0), 1.0], rtol=1e-6)


def test_rough_ground_takes_the_floors_contact_pairs(g1):
    """G1's feet collide with the floor through explicit pairs, which ignore contype: the rough
    scenario moves them to the heightfield (before, G1's "rough" rows walked on the flat floor)."""
    import mujoco
    m = cl.scenario_model(g1, cl.SCENARIOS["rough"])
    rough = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "rough")
    floor = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "floor")
    assert g1.mj.npair == m.npair > 0
    pairs = np.stack([m.pair_geom1, m.pair_geom2], 1)
    assert (pairs == rough).any(1).all() and not (pairs == floor).any()
    # the feet meet the field: standing at home over it, the field's contacts carry the robot
    d = mujoco.MjData(m)
    d.qpos[:] = g1.info.qpos0
    for _ in range(200):
        mujoco.mj_step(m, d)
    geoms = np.stack([d.contact.geom1[:d.ncon], d.contact.geom2[:d.ncon]], 1)
    assert d.ncon > 0 and (geoms == rough).any(1).all()


def test_the_feet_are_read_by_their_geoms_in_the_scenarios_model(go1, g1):
    """The feet's contact flags map the colliding geoms' ids to feet: in the rough scenario's
    model (compiled again, the heightfield added to the world body) the feet are other ids than
    in the robot's model (before: the Go1's 16-42 read at 21-56 with the visual meshes kept, and
    one off without them), so the closed loop reads them by name (``on_model``)."""
    import mujoco

    from stride_jax.robots import RobotError
    from stride_jax.sim import model as sim_model
    for sm in (go1, g1):
        m = cl.scenario_model(sm, cl.SCENARIOS["rough"])
        assert m.ngeom == sm.mj.ngeom + 1  # visual meshes left out as in the robot's model
        moved = sim_model.on_model(sm, m)
        for i, foot in enumerate(sm.robot.feet):
            ids = moved.foot_geoms[i][moved.foot_geoms[i] >= 0]
            assert [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, int(g)) for g in ids] == \
                list(foot.geoms)
            assert (moved.geom_foot[ids] == i).all()
        assert (moved.geom_foot >= 0).sum() == (sm.geom_foot >= 0).sum()
        assert moved.mj is m and (moved.foot_geoms != sm.foot_geoms).any()
    with pytest.raises(RobotError, match="only geoms may differ"):
        sim_model.on_model(go1, g1.mj)


def _fake_step(q, qd, ctrl, key):  # the robot stands still: planner plumbing only
    return q, qd


def test_gait_parameters_are_held_per_rollout(go1):
    cfg = planning_lib.PlanningConfig(gait=True)
    planning = planning_lib.make_planning(cfg, envs.config("go1"), go1, _fake_step)
    q0 = planning_lib.augment(jnp.asarray(go1.info.qpos0), jnp.array([1.0, 0, 0]))
    qd0 = jnp.zeros(go1.mj.nv)
    trot, pace = gait.named("trot", freq=2.0), gait.named("pace", freq=3.5)
    u1, u2 = gait.join_action(jnp.zeros(12), trot), gait.join_action(jnp.zeros(12), pace)
    q1, _ = planning.dynamics(q0, qd0, u1, jax.random.key(0))
    q2, _ = planning.dynamics(q1, qd0, u2, jax.random.key(1))
    a1, a2 = planning_lib.split(q1, go1.mj.nq), planning_lib.split(q2, go1.mj.nq)
    np.testing.assert_allclose(a1.clock, 2.0 * 0.02, rtol=1e-6)
    np.testing.assert_allclose(a2.clock, 2 * 2.0 * 0.02, rtol=1e-6)  # still trot's frequency
    np.testing.assert_array_equal(a2.gait[2:], trot.offsets)
    np.testing.assert_array_equal(planning.ctrl(q1, u2), planning.ctrl(q1, u1))
    with pytest.raises(ValueError, match="planner state"):
        planning_lib.split(jnp.zeros(5), go1.mj.nq)
    # the job builds its planning inside the jitted episode: the gait's nominal plan is a constant
    traced = jax.eval_shape(lambda: jnp.asarray(planning_lib.make_planning(
        cfg, envs.config("go1"), go1, _fake_step).nominal_u))
    assert traced.shape == (12 + gait.N_GAIT,)


def test_learned_reward_and_value_drive_the_planner(go1):
    env_cfg = envs.config("go1")
    obs_n = envs.obs_size(env_cfg, 12)
    lc = learned.LearnedConfig(width=8, depth=1)
    r_params = learned.init(jax.random.key(0), lc, jnp.ones((4, obs_n + 12)), jnp.ones(4))
    v_params = learned.init(jax.random.key(1), lc, jnp.ones((4, obs_n)), jnp.ones(4))
    cfg = cl.ClosedLoopConfig(mppi=mppi.MPPIConfig(samples=8, horizon=3))
    planning = planning_lib.make_planning(cfg.planning, env_cfg, go1, _fake_step,
                                          learned_params=(r_params, v_params))
    planner = planning_lib.make_planner(planning, planning_lib.mppi_config(cfg.mppi, cfg.planning,
                                                                           planning))
    q0 = planning_lib.augment(jnp.asarray(go1.info.qpos0), jnp.array([1.0, 0, 0]))
    u, _, info = jax.jit(planner.step)(planner.init(jax.random.key(0)), q0, jnp.zeros(18))
    assert u.shape == (12,) and np.isfinite(info.costs).all()
    assert np.ptp(np.asarray(info.costs)) > 0  # the learned reward tells samples apart
    # learned_track_weight adds the quadratic tracking term: 1 m/s short of the command costs
    # weight x dt x 1 more per step
    track_cfg = dataclasses.replace(cfg.planning, learned_track_weight=5.0)
    track = planning_lib.make_planning(track_cfg, env_cfg, go1, _fake_step,
                                       learned_params=(r_params, v_params))
    u0 = jnp.zeros(12)
    extra = track.cost(q0, jnp.zeros(18), u0, 0) - planning.cost(q0, jnp.zeros(18), u0, 0)
    assert float(extra) == pytest.approx(5.0 * 0.02 * 1.0, rel=1e-5)


def test_the_task_clock_runs_inside_rollouts_for_a_clocked_policy(go1):
    """The G1 task observes a gait clock: inside MPPI rollouts it must advance as in the
    environment (the policy's candidates read it); the Go1 task has none and keeps it at rest."""
    from stride_jax.sim import model as sim_model

    hold = lambda q, qd, ctrl, key: (q, qd)
    for sm in (sim_model.load("g1"), go1):
        env_cfg = envs.config(sm.robot.name)
        planning = planning_lib.make_planning(planning_lib.PlanningConfig(), env_cfg, sm, hold)
        q_aug = planning_lib.augment(jnp.asarray(sm.info.qpos0), jnp.zeros(3), 0.25)
        q2, _ = planning.dynamics(q_aug, jnp.zeros(sm.mj.nv), jnp.zeros(sm.info.nu),
                                  jax.random.key(0))
        step = env_cfg.gait_hz * sm.robot.ctrl_dt
        assert float(planning_lib.split(q2, sm.mj.nq).clock) == pytest.approx(0.25 + step)
        assert planning.clock_hz == env_cfg.gait_hz
    assert envs.config("g1").gait_hz > 0 and envs.config("go1").gait_hz == 0


def test_a_policy_of_another_robot_is_a_clear_error(tmp_path):
    cfg = cl.ClosedLoopConfig(robot="g1", models="policy", scenarios="walk",
                              policy="results/policies/ppo_go1", out=str(tmp_path))
    with pytest.raises(ValueError, match="drives go1, not g1"):
        cl.run(cfg)


def test_mppi_settings_are_one_nested_config_with_the_old_flags_kept():
    """`--mppi.samples` sets the planner's samples; the flat `--samples` of recorded commands
    still does; a planner without a policy gets no policy candidates."""
    import argparse

    from stride_jax import config

    parser = argparse.ArgumentParser()
    config.add_flags(parser, cl.ClosedLoopConfig)
    new = config.from_flags(cl.ClosedLoopConfig, parser.parse_args(
        ["--mppi.samples", "64", "--mppi.risk", "cvar"]))
    old = config.from_flags(cl.ClosedLoopConfig, parser.parse_args(
        ["--samples", "64", "--risk", "cvar", "--policy-noise"]))
    assert new.mppi.samples == old.mppi.samples == 64 and new.mppi.risk == old.mppi.risk == "cvar"
    assert old.mppi.policy_noise and not new.mppi.policy_noise
    assert cl.ClosedLoopConfig().mppi == mppi.MPPIConfig()  # one source of MPPI's defaults
    planning = planning_lib.Planning(None, None, None, None, None, np.zeros(2), np.ones(2),
                                     (0.1, 0.2), np.zeros(2))
    got = planning_lib.mppi_config(dataclasses.replace(new.mppi, policy_samples=8),
                                   new.planning, planning)
    assert got.policy_samples == 0 and got.noise_std == (0.1, 0.2) and got.samples == 64


def test_pushes_move_the_base_sideways_by_the_impulse(go1, held):
    sc = dataclasses.replace(cl.SCENARIOS["push"], pushes=((0.02, 0.06, 0.0, 0.4),))
    mass = float(go1.mj.body_mass.sum())
    pushes = cl.push_schedule(sc, mass)
    np.testing.assert_allclose(pushes[0], [0.02, 0.08, 0.0, mass * 0.4 / 0.06], rtol=1e-6)
    assert not pushes[1:].any()
    np.testing.assert_allclose(scenarios.push_at(pushes, 0.05), [0.0, mass * 0.4 / 0.06], rtol=1e-6)
    assert not np.asarray(scenarios.push_at(pushes, 0.08)).any()
    with pytest.raises(ValueError, match="more than 4 pushes"):
        cl.push_schedule(dataclasses.replace(sc, pushes=sc.pushes * 5), mass)
    # A robot holding its home pose (the "policy" of the held episode at a zero command): the
    # push's impulse shows as sideways base velocity, which the unpushed episode lacks.
    run = held
    starts, values = cl.schedule(dataclasses.replace(sc, commands=((0.0, 0.0, 0.0, 0.0),)))
    pushed = run(starts, values, jnp.asarray(pushes), *_NO_LIMITS, _LEVEL)
    still = run(starts, values, jnp.zeros_like(pushes), *_NO_LIMITS, _LEVEL)
    vy_world = float(pushed.v_base[3, 1] - still.v_base[3, 1])  # base frame ~ world frame here
    assert 0.1 < vy_world < 0.45, vy_world  # at most the free-body 0.4 m/s, less what the feet hold


def test_planning_settings_are_one_nested_config_with_the_old_flags_kept():
    """`--planning.noise-std` and the rest of the planner's task settings are one nested
    `PlanningConfig`; the flat flags of recorded commands (`--noise-std`, `--gait` ...) give the
    same config, in the closed loop and in the Dreamer-MPC ablation that shares it."""
    import argparse

    from stride_jax import config
    from stride_jax.jobs import dreamer_mpc

    values = dict(noise_std="0.05", prior_noise_std="0.1", plan_range="0.4", gait_noise="0.3",
                  value_weight="0.5", fall_cost="2.0", track_weight="3.0")
    parser = argparse.ArgumentParser()
    config.add_flags(parser, cl.ClosedLoopConfig)
    new = config.from_flags(cl.ClosedLoopConfig, parser.parse_args(
        [a for k, v in values.items() for a in ("--planning." + k.replace("_", "-"), v)]
        + ["--planning.gait"]), cl.PRESETS["tiny"])
    old = config.from_flags(cl.ClosedLoopConfig, parser.parse_args(
        [a for k, v in values.items() for a in ("--" + k.replace("_", "-"), v)] + ["--gait"]),
        cl.PRESETS["tiny"])
    want = planning_lib.PlanningConfig(gait=True, **{k: float(v) for k, v in values.items()})
    assert new == old == dataclasses.replace(cl.PRESETS["tiny"], planning=want)
    assert cl.ClosedLoopConfig().planning == planning_lib.PlanningConfig()  # one source
    assert "--planning.noise-std" in config.to_flags(new)

    parser = argparse.ArgumentParser()
    config.add_flags(parser, dreamer_mpc.AblationConfig)
    new = config.from_flags(dreamer_mpc.AblationConfig, parser.parse_args(
        ["--planning.noise-std", "0.1", "--planning.prior-noise-std", "0.05"]))
    old = config.from_flags(dreamer_mpc.AblationConfig, parser.parse_args(
        ["--noise-std", "0.1", "--prior-noise-std", "0.05"]))
    assert new == old and new.planning == planning_lib.PlanningConfig(noise_std=0.1,
                                                                      prior_noise_std=0.05)
    assert dreamer_mpc.variant_config(new, "prior").planning == new.planning


def test_disturbance_observer_finds_a_persistent_push_and_rollouts_carry_it(go1):
    """Offset-free planning: the model (here: standing still) misses a constant base
    acceleration of the real robot; the observer's estimate converges to it, is bounded, and
    the planner's rollouts then predict the real step. Off, the state's entries change nothing."""
    nq, nv, dt = go1.mj.nq, go1.mj.nv, go1.robot.ctrl_dt
    cfg = planning_lib.PlanningConfig(observer_gain=0.2, observer_limit=6.0, observer_angular=True)
    planning = planning_lib.make_planning(cfg, envs.config("go1"), go1, _fake_step)
    true = jnp.array([-3.3, 0.4, 0.6, 0.0, -1.0, 0.2])  # a slope's pull, a tilt's roll
    q, qd, u = jnp.asarray(go1.info.qpos0), jnp.zeros(nv), jnp.zeros(12)
    qd_real = qd.at[:6].add(dt * true)
    dist = jnp.zeros(planning_lib.N_DIST)
    update = jax.jit(lambda dist: planning_lib.update_disturbance(
        planning, planning_lib.augment(q, jnp.array([1.0, 0, 0]), disturbance=dist), qd, u,
        qd_real, dt, jax.random.key(0)))
    for _ in range(80):
        dist = update(dist)
    np.testing.assert_allclose(dist, true, atol=1e-3)
    q_aug = planning_lib.augment(q, jnp.array([1.0, 0, 0]), disturbance=dist)
    q2, qd2 = planning.dynamics(q_aug, qd, u, jax.random.key(1))
    np.testing.assert_allclose(qd2, qd_real, atol=1e-4)
    np.testing.assert_allclose(q2[:3], q[:3] + dt * dt * true[:3], atol=1e-6)
    np.testing.assert_array_equal(planning_lib.split(q2, nq).disturbance, dist)  # held
    # bounded: a push beyond the limit saturates there
    big = planning_lib.update_disturbance(planning, q_aug, qd, u, qd.at[0].add(dt * 50.0), dt,
                                          jax.random.key(0))
    assert float(big[0]) == pytest.approx(6.0)
    # by default only the linear part is estimated
    linear = planning_lib.make_planning(dataclasses.replace(cfg, observer_angular=False),
                                        envs.config("go1"), go1, _fake_step)
    d1 = planning_lib.update_disturbance(linear, planning_lib.augment(q, jnp.zeros(3)), qd, u,
                                         qd_real, dt, jax.random.key(0))
    np.testing.assert_allclose(d1, jnp.r_[0.2 * true[:3], 0, 0, 0], rtol=1e-5, atol=1e-6)
    # off: the model's own step, whatever the state's disturbance entries hold
    off = planning_lib.make_planning(planning_lib.PlanningConfig(), envs.config("go1"), go1,
                                     _fake_step)
    _, qd_off = off.dynamics(q_aug, qd, u, jax.random.key(1))
    np.testing.assert_array_equal(qd_off, qd)


def test_model_gravity_tells_the_planners_model_the_sensed_gravity(go1):
    """``model_gravity``: the planner's model step receives the state's sensed gravity (held in
    the planner state over a rollout); off, it is called as before (no ``down``). Through
    :func:`learned_step` a Lagrangian model takes it and a next-observation model is called
    without it."""
    from stride_jax.control.episode import learned_step
    from stride_jax.dynamics import models
    from stride_jax.types import ModelSpec
    nq, nv = go1.mj.nq, go1.mj.nv
    seen = []

    def step(q, qd, ctrl, key, **told):
        seen.append(told)
        return q, qd

    tilt = jnp.asarray(scenarios.tilted(jnp.array([0.0, 0.0, -9.81]), 0.3) / 9.81)
    q_aug = planning_lib.augment(jnp.asarray(go1.info.qpos0), jnp.array([1.0, 0, 0]),
                                 gravity=tilt)
    for on in (True, False):
        planning = planning_lib.make_planning(planning_lib.PlanningConfig(model_gravity=on),
                                              envs.config("go1"), go1, step)
        q2, _ = planning.dynamics(q_aug, jnp.zeros(nv), jnp.zeros(12), jax.random.key(0))
        np.testing.assert_array_equal(planning_lib.split(q2, nq).gravity, tilt)  # held
    assert set(seen[0]) == {"down"} and seen[1] == {}
    np.testing.assert_array_equal(seen[0]["down"], tilt)

    calls = []
    for name in ("delan", "onn"):
        m = models.make(name, ModelSpec(nq=nq, nv=nv, floating_base=True))
        fake = m._replace(step=lambda p, q, qd, c, k, nfe=None, **kw: calls.append(kw) or (q, qd))
        learned_step(fake, {})(q_aug[:nq], jnp.zeros(nv), jnp.zeros(nv), None, down=tilt)
    assert set(calls[0]) == {"down"} and calls[1] == {}


def test_learned_step_sets_a_generative_residuals_evaluations(go1):
    """``nfe`` reaches a stochastic model's step and not a deterministic one's (which has no
    residual samples); unset, neither is given one (each model as trained); below 1 it is an
    error."""
    from stride_jax.control.episode import learned_step
    from stride_jax.dynamics import models
    from stride_jax.types import ModelSpec
    nq, nv = go1.mj.nq, go1.mj.nv
    q = jnp.zeros(nq).at[3].set(1.0)
    got = {}
    for name in ("stride", "delan"):
        m = models.make(name, ModelSpec(nq=nq, nv=nv, floating_base=True))
        fake = m._replace(step=lambda p, q, qd, c, k, n=name, **kw: got.setdefault(n, []).append(kw)
                          or (q, qd))
        for nfe in (8, None):
            learned_step(fake, {}, nfe=nfe)(q, jnp.zeros(nv), jnp.zeros(nv), None)
    assert models.make("stride", ModelSpec(nq=nq, nv=nv, floating_base=True)).stochastic
    assert got["stride"] == [{"nfe": 8}, {}] and got["delan"] == [{}, {}]
    with pytest.raises(ValueError, match="nfe=0"):
        learned_step(fake, {}, nfe=0)


_NO_LIMITS = (jnp.full(3, -jnp.inf, jnp.float32), jnp.full(3, jnp.inf, jnp.float32))  # clips nothing
_LEVEL = np.zeros(2, np.float32)  # no tilt schedule: the model's own gravity


@pytest.fixture(scope="module")
def held(go1):
    """One jitted 5-step episode on flat ground (shared by the pushes and governor tests: one
    compilation) of a "policy" that holds the home pose, moved by the forward command it sees:
    ``run(starts, values, pushes, lo, hi, tilt) -> Trace``."""
    mx = mjx.put_model(go1.mj)
    planning = planning_lib.make_planning(cl.PRESETS["tiny"].planning, envs.config("go1"), go1,
                                          cl.mjx_step_fn(go1, mx))
    nq = go1.mj.nq
    planning = planning._replace(policy=lambda q, qd: jnp.asarray(planning.nominal_u) + 0.1 * q[nq])
    return jax.jit(lambda starts, values, pushes, lo, hi, tilt: cl.run_episode(
        go1, mx, envs.contact_slots(mx), planning, None, 5, starts, values, jax.random.key(0),
        pushes=pushes, limits=(lo, hi), tilt=tilt))



def test_a_command_governor_clips_what_the_controller_sees_and_the_trace_keeps_the_ask(held):
    run, no_push = held, jnp.zeros((4, 4))
    lo, hi = jnp.array([0.0, -0.3, -0.5]), jnp.array([1.0, 0.3, 0.5])

    def episode(command, limits):
        starts, values = cl.schedule(dataclasses.replace(cl.SCENARIOS["walk"], commands=((0.0, *command),)))
        return run(starts, values, no_push, *limits, _LEVEL)

    governed, asked_within = episode((2.0, 0.6, 0.0), (lo, hi)), episode((1.0, 0.3, 0.0), _NO_LIMITS)
    np.testing.assert_array_equal(governed.action, asked_within.action)  # it acted on (1.0, 0.3, 0)
    np.testing.assert_allclose(governed.command[:, :2], [[2.0, 0.6]] * 5)  # the metrics see the ask
    free = episode((2.0, 0.6, 0.0), _NO_LIMITS)
    assert not np.allclose(free.action, governed.action)


def test_a_tilting_ground_builds_the_slope_up_and_a_still_one_is_the_models_own_gravity(held):
    g = np.array([0.0, 0.0, -9.81], np.float32)
    tilt = cl.tilt_schedule(cl.SCENARIOS["tilt"])
    np.testing.assert_allclose(scenarios.gravity_at(tilt, 0.0, g), g, atol=1e-6)  # level at first
    half = np.asarray(scenarios.gravity_at(tilt, 1.0, g))
    np.testing.assert_allclose(np.degrees(np.arctan2(-half[0], -half[2])), 10.0, rtol=1e-5)
    for t in (2.0, 5.0):
        gt = np.asarray(scenarios.gravity_at(tilt, t, g))
        np.testing.assert_allclose(np.degrees(np.arctan2(-gt[0], -gt[2])), 20.0, rtol=1e-5)
        np.testing.assert_allclose(np.linalg.norm(gt), 9.81, rtol=1e-6)
    slope = cl.tilt_schedule(cl.SCENARIOS["slope"])  # no build-up: whatever the model has
    np.testing.assert_array_equal(scenarios.gravity_at(slope, 0.0, half), half)
    # In an episode: the still schedule is bit-identical to none; a fast tilt pulls the robot
    # back (downhill, -x) against the level run.
    starts, values = cl.schedule(cl.SCENARIOS["walk"])
    args = (starts, values, jnp.zeros((4, 4)), *_NO_LIMITS)
    level = held(*args, _LEVEL)
    still = held(*args, slope)
    for a, b in zip(jax.tree.leaves(level), jax.tree.leaves(still)):
        np.testing.assert_array_equal(a, b)
    # --slope-deg: the angle of scenarios with a slope, in their names; the others untouched.
    cfg = cl.ClosedLoopConfig(slope_deg=15.0, seconds=3.0)
    t15 = cl.scenario(cfg, "tilt")
    assert (t15.name, t15.slope_deg, t15.tilt_s, t15.seconds) == ("tilt15", 15.0, 2.0, 3.0)
    assert cl.scenario(cfg, "soft").name == "soft" and cl.scenario(cfg, "soft").slope_deg == 0.0
    # --rough-cm: the bump height of rough-ground scenarios, in their names.
    low = cl.scenario(cl.ClosedLoopConfig(rough_cm=2.0), "rough")
    assert (low.name, low.rough_m) == ("rough2", 0.02)
    assert cl.scenario(cl.ClosedLoopConfig(rough_cm=2.0), "slope").rough_m == 0.0
    # --push-scale and --friction: the pushes' strength and the lowered friction, in the names.
    hard = cl.scenario(cl.ClosedLoopConfig(push_scale=3.0), "push")
    assert hard.name == "push3x"
    assert [p[3] for p in hard.pushes] == [3 * p[3] for p in cl.SCENARIOS["push"].pushes]
    assert cl.scenario(cl.ClosedLoopConfig(push_scale=3.0), "soft").pushes == ()
    icy = cl.scenario(cl.ClosedLoopConfig(friction=0.15), "low_friction")
    assert (icy.name, icy.friction) == ("low_friction0.15", 0.15)
    assert cl.scenario(cl.ClosedLoopConfig(friction=0.15), "slope").friction == 1.0
    with pytest.raises(ValueError, match="friction"):
        cl.scenario(cl.ClosedLoopConfig(friction=-0.1), "low_friction")
    heavy = cl.scenario(cl.ClosedLoopConfig(payload=0.4), "payload")
    assert (heavy.name, heavy.payload) == ("payload0.4", 0.4)
    assert cl.scenario(cl.ClosedLoopConfig(payload=0.4), "walk").payload == 0.0
    worn = cl.scenario(cl.ClosedLoopConfig(payload=0.4, payload_body="torso_link"), "payload")
    assert (worn.name, worn.payload, worn.payload_body) == ("payload0.4_on_torso_link", 0.4, "torso_link")
    assert cl.scenario(cl.ClosedLoopConfig(payload_body="torso_link"), "walk").payload_body == ""
    tilted = held(*args, np.array([np.deg2rad(30.0), 0.02], np.float32))
    assert np.asarray(tilted.v_base)[-1, 0] < np.asarray(level.v_base)[-1, 0] - 0.05


@pytest.mark.slow  # progress lines, rows, skip on rerun: test_a_chunked_run_killed_mid_episode_resumes_to_the_same_rows
def test_a_run_logs_its_progress_writes_its_row_and_resumes(tmp_path):
    """The closed-loop job end to end at tiny size: progress lines while an episode runs (a
    planner through MJX runs minutes per episode), the row in closed_loop.json, and a second
    call skipping the finished pair."""
    cfg = cl.ClosedLoopConfig(models="policy", scenarios="walk", seconds=0.2, progress_s=0.1,
                              settle_s=0.0, policy="results/policies/ppo_go1", out=str(tmp_path))
    lines = []
    rows = cl.run(cfg, log=lines.append)
    assert [r["model"] for r in rows] == ["policy"] and np.isfinite(rows[0]["vel_rmse"])
    assert 0 < rows[0]["controller_ms"] <= rows[0]["controller_ms_max"]  # its own period, apart
    assert "| controller ms |" in (tmp_path / "closed_loop.md").read_text()
    ticks = [x for x in lines if "s simulated" in x]
    assert [t.split(":")[1].split(" of")[0].strip() for t in ticks] == ["0.1", "0.2"]
    again = []
    assert cl.run(cfg, log=again.append) == rows and not any("simulated" in x for x in again)


def test_a_run_records_the_commit_it_started_from(tmp_path, monkeypatch):
    """A checkout that moves on while a run goes (another commit, a switched branch) does not
    relabel the run's results: the code is read once, at its start."""
    checkout = {"commit": "started-here"}
    monkeypatch.setattr(cl, "code_version", lambda: checkout["commit"])
    cfg = cl.ClosedLoopConfig(models="policy", scenarios="walk", seconds=0.1, settle_s=0.0,
                              policy="results/policies/ppo_go1", out=str(tmp_path))
    cl.run(cfg, log=lambda _: checkout.update(commit="moved-on"))  # it moves once the run logs
    assert json.loads((tmp_path / "closed_loop.json").read_text())["env"]["code"] == "started-here"


def test_a_payload_on_a_body_the_robot_lacks_fails_before_any_episode(tmp_path):
    cfg = cl.ClosedLoopConfig(models="policy", scenarios="walk,payload", seconds=0.2, settle_s=0.0,
                              payload_body="backpack", policy="results/policies/ppo_go1",
                              out=str(tmp_path))
    lines = []
    with pytest.raises(ValueError, match="payload body 'backpack' is not a body of 'go1'"):
        cl.run(cfg, log=lines.append)
    assert not any("simulated" in x for x in lines) and not (tmp_path / "closed_loop.json").exists()


_CHUNKED = dict(models="policy", scenarios="walk", seconds=0.2, settle_s=0.0, progress_s=0.0,
                policy="results/policies/ppo_go1", episodes=2)


def _same_rows_and_traces(rows, ref, a_dir, b_dir, rel):
    for r, r0 in zip(rows, ref, strict=True):
        for k, v in r0.items():
            if k not in ("ms_per_step", "controller_ms", "controller_ms_max", "compile_s"):
                assert r[k] == (pytest.approx(v, rel=rel) if isinstance(v, float) else v), k
    for f in ("trace_walk_policy.npz", "trace_walk_policy_seed1.npz"):
        a, b = np.load(a_dir / f), np.load(b_dir / f)
        for k in a.files:
            np.testing.assert_allclose(b[k], a[k], rtol=rel, atol=rel, err_msg=k)


def test_a_chunked_run_killed_mid_episode_resumes_to_the_same_rows(tmp_path, monkeypatch):
    """``chunk_s``: episodes run chunk by chunk, their state saved after each; a run killed after
    its first chunk resumes there when called again, and gives the rows and traces of the same
    run uninterrupted (episodes side by side, so the saved state carries a batch of planner keys
    and simulations); nothing partial is left once the row is written. (Against a run without
    chunks: test_chunks_give_the_rows_of_one_program, slow.)"""
    cfg = cl.ClosedLoopConfig(out=str(tmp_path / "whole"), chunk_s=0.08, **_CHUNKED)
    whole = cl.run(cfg, log=lambda *_: None)
    cfg = dataclasses.replace(cfg, out=str(tmp_path / "chunked"))
    assert cl._chunk_steps(cfg.chunk_s, 0.02, 10) == 4  # 3 chunks of 4 steps for 10
    save, saved = cl._save_state, []

    def killed_after_one(path, *a):
        save(path, *a)
        saved.append(path)
        raise KeyboardInterrupt("killed")

    monkeypatch.setattr(cl, "_save_state", killed_after_one)
    with pytest.raises(KeyboardInterrupt):
        cl.run(cfg, log=lambda *_: None)
    assert saved and saved[0].is_file() and not (tmp_path / "chunked" / "closed_loop.json").exists()
    monkeypatch.setattr(cl, "_save_state", save)
    lines = []
    rows = cl.run(dataclasses.replace(cfg, progress_s=0.02), log=lines.append)
    assert any("resumed at 4 of 10 steps" in x for x in lines)
    ticks = [x.split(":")[1].split(" of")[0].strip() for x in lines if "s simulated" in x]
    assert ticks == [f"{0.02 * k:.1f}" for k in range(5, 11)]  # none past the end (12 run)
    assert not saved[0].exists() and not saved[0].parent.exists()  # nothing partial left
    _same_rows_and_traces(rows, whole, tmp_path / "whole", tmp_path / "chunked", 1e-6)
    # killed after its last chunk but before its rows (timing the controller, say): the saved
    # state is kept, and the next call resumes at the episode's end, running no chunk again
    cfg = dataclasses.replace(cfg, out=str(tmp_path / "timed"), controller_repeats=1)

    def killed_timing(*a, **k):
        raise KeyboardInterrupt("killed while timing the controller")

    monkeypatch.setattr(cl, "wall_times", killed_timing)
    with pytest.raises(KeyboardInterrupt):
        cl.run(cfg, log=lambda *_: None)
    assert list((tmp_path / "timed" / "partial").glob("*.npz"))
    assert not (tmp_path / "timed" / "closed_loop.json").exists()
    monkeypatch.undo()
    lines = []
    rows = cl.run(dataclasses.replace(cfg, progress_s=0.02), log=lines.append)
    assert any("resumed at 10 of 10 steps" in x for x in lines), lines
    assert not any("s simulated" in x for x in lines)  # no chunk run again
    assert not (tmp_path / "timed" / "partial").exists()
    _same_rows_and_traces(rows, whole, tmp_path / "whole", tmp_path / "timed", 1e-6)
    with pytest.raises(ValueError, match="chunk-s"):
        cl.ClosedLoopConfig(chunk_s=-1.0)
    # a saved state comes back with its typed keys, and only for its own run and structure
    state = {"x": jnp.arange(3.0), "key": jax.random.key(5)}
    path = tmp_path / "state.npz"
    cl._save_state(path, state, [], 4, 1.5, "this run")
    carry, traces, steps, run_s = cl._load_state(path, state, "this run")
    assert (traces, steps, run_s) == ([], 4, 1.5)
    np.testing.assert_array_equal(carry["x"], state["x"])
    np.testing.assert_array_equal(jax.random.key_data(carry["key"]),
                                  jax.random.key_data(state["key"]))
    assert isinstance(cl._load_state(path, state, "another run"), str)
    assert "other shapes" in cl._load_state(path, {**state, "x": jnp.arange(4.0)}, "this run")
    assert cl._load_state(tmp_path / "none.npz", state, "this run") is None


def test_a_saved_state_resumes_across_a_setting_added_since_at_its_default(tmp_path):
    """A state saved before the code gained a setting is this run's where the new setting is
    at its default (the saved run ran so before it existed), and another run's where it is
    not; a setting the saved run named at another value is another run's as ever."""
    state = {"x": jnp.arange(3.0), "key": jax.random.key(5)}

    def ident(**planning):
        return json.dumps(dict(settings=dict(planning=dict(observer_gain=0.3, **planning)),
                               model="oracle"), sort_keys=True)

    path = tmp_path / "state.npz"
    cl._save_state(path, state, [], 4, 1.5, ident())  # before trust_component existed
    assert cl._load_state(path, state, ident(trust_component="norm"))[2] == 4
    said = cl._load_state(path, state, ident(trust_component="down"))
    assert "planning.trust_component: (absent) -> down" in said, said
    assert isinstance(cl._load_state(path, state, ident(observer_gain_x=1.0)), str)  # unknown
    cl._save_state(path, state, [], 4, 1.5, ident(trust_component="down"))
    assert isinstance(cl._load_state(path, state, ident(trust_component="norm")), str)


def test_a_saved_state_of_another_run_is_set_aside_with_the_reason_not_overwritten(tmp_path):
    """A chunked episode whose saved state is another run's (a setting changed between the call
    cut by its limit and the call resuming it) says which settings differ, keeps that state
    beside under another name, and runs from its first step; the set-aside file is never
    overwritten by the new run's own states. Settings that only time the controller
    (``controller_repeats``) do not make another run."""
    from stride_jax.control.episode import Trace

    def ident(**planning):
        return json.dumps(dict(settings=dict(planning=dict(observer_gain=0.3, **planning)),
                               model="onn"), sort_keys=True)

    start = lambda x: {"x": x, "key": jax.random.key(0)}
    resume = lambda carry, steps, x: ({**carry, "x": carry["x"] + 1.0}, Trace(
        *(jnp.full((2,), steps, jnp.float32) for _ in Trace._fields)))
    path = tmp_path / "partial" / "walk_onn.npz"
    old = start(jnp.zeros(3))
    cl._save_state(path, {**old, "x": old["x"] + 7.0}, [], 2, 0.5, ident())
    before = path.read_bytes()
    lines = []
    traces, _ = cl._chunked((start, resume), (jnp.zeros(3),), 4, 2, False, path,
                            ident(latency_auto=True), {"label": "walk onn"}, lines.append)
    said = " ".join(lines)
    assert "is not resumed" in said and "planning.latency_auto: (absent) -> True" in said, said
    aside = tmp_path / "partial" / "walk_onn.stale0.npz"
    assert aside.read_bytes() == before  # kept whole
    assert path.exists()  # the run's own, until its rows are written (cl._drop_state)
    np.testing.assert_array_equal(traces.t, [0, 0, 2, 2])  # from the first step, not the 2nd
    assert "walk_onn.stale0.npz" in said
    # a second set-aside takes the next name
    cl._save_state(path, old, [], 2, 0.5, ident(observer_gain_x=1))
    cl._chunked((start, resume), (jnp.zeros(3),), 4, 2, False, path, ident(), {"label": "w"},
                lambda *_: None)
    assert (tmp_path / "partial" / "walk_onn.stale1.npz").is_file() and aside.is_file()
    cfg = cl.ClosedLoopConfig()
    assert "controller_repeats" in dataclasses.asdict(cfg) and "controller_repeats" in cl._PER_RUN


def _together_and_apart(tmp_path, **kw):
    """The rows of ``kw`` run one scenario at a time and with ``together``, each checked to be
    the other's to float rounding (traces too); ``(together's rows, its log)``."""
    apart = cl.run(cl.ClosedLoopConfig(out=str(tmp_path / "apart"), **kw), log=lambda *_: None)
    lines = []
    together = cl.run(cl.ClosedLoopConfig(out=str(tmp_path / "together"), together=True, **kw),
                      log=lines.append)
    key = lambda r: (r["scenario"], r["model"], r["seed"])
    ref = {key(r): r for r in apart}
    assert sorted(ref) == sorted(key(r) for r in together)
    for r in together:
        for k, v in ref[key(r)].items():
            if k not in ("ms_per_step", "controller_ms", "controller_ms_max", "compile_s",
                         "side_by_side"):
                assert r[k] == (pytest.approx(v, rel=1e-5, abs=1e-6) if isinstance(v, float)
                                else v), (key(r), k)
    for f in sorted((tmp_path / "apart").glob("trace_*.npz")):
        a, b = np.load(f), np.load(tmp_path / "together" / f.name)
        for k in a.files:  # other batch shapes round otherwise: 2e-5 relative seen
            np.testing.assert_allclose(b[k], a[k], rtol=1e-4, atol=1e-5, err_msg=f"{f.name} {k}")
    return together, lines


def test_scenarios_run_together_give_the_rows_they_give_apart(tmp_path):
    """``together``: the scenarios whose worlds differ in values alone (pushes, friction, a
    command schedule) run side by side in one program per model, each episode in its own
    world; rough ground (another model structure) runs apart. The rows and traces are those of
    the scenarios run one at a time, to float rounding; the rows say how many ran side by side
    and which scenarios. (The oracle, planning through its episode's own world:
    test_the_oracle_plans_through_its_own_world_together, slow.)"""
    rows, _ = _together_and_apart(
        tmp_path, models="policy", scenarios="push,low_friction,rough,changes", seconds=0.2,
        settle_s=0.0, progress_s=0.0, policy="results/policies/ppo_go1", episodes=2,
        controller_repeats=0, rough_cm=2)
    assert len(rows) == 8
    for r in rows:
        if r["scenario"] == "rough2":
            assert r["side_by_side"] == 2 and "scenarios_together" not in r
        else:  # three worlds x two episodes
            assert r["side_by_side"] == 6
            assert r["scenarios_together"] == "push+low_friction+changes"
    # the worlds differ (so the match above says each episode met its own): friction at once
    t = {n: np.load(tmp_path / "together" / f"trace_{n}_policy.npz")
         for n in ("push", "low_friction")}
    assert np.abs(t["push"]["v_base"] - t["low_friction"]["v_base"]).max() > 1e-3


@pytest.mark.slow  # MJX planning compiled four times; fast: test_scenarios_run_together_give_the_rows_they_give_apart
def test_the_oracle_plans_through_its_own_world_together(tmp_path):
    """The oracle side by side plans each episode through that episode's own world (its
    friction, its pushes), as it does run apart."""
    rows, _ = _together_and_apart(
        tmp_path, models="oracle", scenarios="push,low_friction", seconds=0.1, settle_s=0.0,
        progress_s=0.0, policy="results/policies/ppo_go1", controller_repeats=0,
        mppi=mppi.MPPIConfig(samples=4, horizon=2))
    assert [r["side_by_side"] for r in rows] == [2, 2]


@pytest.mark.slow  # a second compile of the episode; fast: test_a_chunked_run_killed_mid_episode_resumes_to_the_same_rows
def test_chunks_give_the_rows_of_one_program(tmp_path):
    """An episode run in chunks gives the rows and traces of the same episode as one program (to
    float rounding: other programs)."""
    plain = cl.run(cl.ClosedLoopConfig(out=str(tmp_path / "plain"), **_CHUNKED), log=lambda *_: None)
    rows = cl.run(cl.ClosedLoopConfig(out=str(tmp_path / "chunked"), chunk_s=0.08, **_CHUNKED),
                  log=lambda *_: None)
    _same_rows_and_traces(rows, plain, tmp_path / "plain", tmp_path / "chunked", 1e-5)


def test_runs_of_one_kind_of_model_share_one_compiled_episode(tmp_path):
    """A trained model's parameters and data scales are the episode's argument: runs of one
    recipe (trained seeds, whose scales differ in their last bits) compile once, a run with
    another definition (another training configuration) once more, and sharing changes no
    result."""
    from stride_jax.dynamics import checkpoint
    a, b = "results/models/go1_walk/onn-s0", "results/models/go1_walk_tw1_tf0.25/onn-s0"
    c = tmp_path / "onn_scaled"  # the same run with its data scales moved by 1%
    shutil.copytree(a, c)
    d = json.loads((c / "model.json").read_text())
    d["scales"]["qd"] = [1.01 * x for x in d["scales"]["qd"]]
    d["definition_sha256"] = checkpoint._digest(d)
    (c / "model.json").write_text(json.dumps(d))
    cfg = cl.ClosedLoopConfig(models=f"onn={a},onn_again={a},onn_scaled={c},onn_other={b}",
                              scenarios="walk", seconds=0.1, settle_s=0.0, progress_s=0.1,
                              mppi=mppi.MPPIConfig(samples=8, horizon=3), out=str(tmp_path))
    lines = []
    rows = cl.run(cfg, log=lines.append)
    compiles = [x.strip() for x in lines if x.endswith("compiling")]
    assert compiles == ["walk onn: compiling", "walk onn_other: compiling"]
    by = {r["model"]: r for r in rows}
    assert by["onn_again"]["vel_rmse"] == by["onn"]["vel_rmse"]
    # the scales are read, not baked in: the same parameters with other scales plan otherwise
    # (that the rebuilt model computes what the scaled one does: test_checkpoint)
    assert by["onn_scaled"]["vel_rmse"] != by["onn"]["vel_rmse"]
    assert by["onn_other"]["vel_rmse"] != by["onn"]["vel_rmse"]


def test_episodes_side_by_side_give_a_row_per_seed_and_the_first_equals_a_single_run(tmp_path):
    """``episodes``: one vmapped program runs a pair's episodes over the seeds; each seed gets
    its row and trace, the first seed's row is the row of a plain run at that seed, the others
    differ (the planner's draws), the summary over seeds counts them, and a second call skips
    them."""
    common = dict(models="onn=results/models/go1_walk/onn-s0", scenarios="walk", seconds=0.1,
                  settle_s=0.0, progress_s=0.0, mppi=mppi.MPPIConfig(samples=8, horizon=3))
    single = cl.run(cl.ClosedLoopConfig(out=str(tmp_path / "one"), seed=3, **common),
                    log=lambda *_: None)
    cfg = cl.ClosedLoopConfig(out=str(tmp_path / "many"), seed=3, episodes=2, **common)
    rows = cl.run(cfg, log=lambda *_: None)
    assert [(r["seed"], r["episode"], r["side_by_side"]) for r in rows] == [(3, 0, 2), (4, 1, 2)]
    np.testing.assert_allclose(rows[0]["vel_rmse"], single[0]["vel_rmse"], rtol=1e-4)
    one = np.load(tmp_path / "one" / "trace_walk_onn.npz")
    first = np.load(tmp_path / "many" / "trace_walk_onn.npz")
    other = np.load(tmp_path / "many" / "trace_walk_onn_seed4.npz")
    # the same draws (batched arithmetic rounds differently: 1e-6 at the first step, growing)
    np.testing.assert_allclose(first["action"][0], one["action"][0], atol=1e-5)
    np.testing.assert_allclose(first["action"], one["action"], atol=2e-3)
    assert np.abs(other["action"] - first["action"]).max() > 2e-2  # other draws
    summary = cl.over_seeds(rows)
    assert [(g["episodes"], g["falls"], g["seeds"]) for g in summary] == [(2, 0, [3, 4])]
    assert "Over seeds" in (tmp_path / "many" / "closed_loop.md").read_text()
    assert cl.run(cfg, log=lambda *_: None) == rows
    with pytest.raises(ValueError, match="episodes"):
        cl.ClosedLoopConfig(episodes=0)


def _part(folder, rows, command):
    folder.mkdir(parents=True)
    (folder / "closed_loop.json").write_text(json.dumps(dict(env=dict(command=command),
                                                             rows=rows)))
    return folder


def _row(scenario, model, vel, fell=False):
    return dict(scenario=scenario, model=model, vel_rmse=vel, fell=fell,
                fall_s=1.5 if fell else None, ms_per_step=10.0)


def test_merged_parts_keep_their_names_and_figures_and_bars_pick_by_part(tmp_path):
    """Merging parts renames a second part's (scenario, model) pair ``model@part``; a scenario
    none of whose rows has a trace keeps its figure (a merge must not blank it); ``select``
    takes each scenario from the first listed part that has it; ``bars`` writes the figure."""
    a = _part(tmp_path / "a", [_row("walk", "stride", 0.07), _row("push", "stride", 0.16),
                               _row("walk", "policy", 0.068)], "first")
    b = _part(tmp_path / "b", [_row("walk", "stride", 0.055), _row("rough", "stride", 0.7, True)],
              "second")
    out = tmp_path / "merged"
    out.mkdir()
    (out / "closed_loop_walk.png").write_bytes(b"kept")
    rows = cl.merge([str(a), str(b)], str(out), "t")
    assert [r["model"] for r in rows] == ["stride", "stride", "policy", "stride@b", "stride"]
    assert [r["part"] for r in rows] == ["a", "a", "a", "b", "b"]
    assert (out / "closed_loop_walk.png").read_bytes() == b"kept"
    assert set(json.loads((out / "closed_loop.json").read_text())["parts"]) == {"a", "b"}

    picked = cl.select(rows, "stride", ("b", "a"))
    assert {sc: (r["part"], r["vel_rmse"]) for sc, r in picked.items()} == {
        "walk": ("b", 0.055), "push": ("a", 0.16), "rough": ("b", 0.7)}
    assert set(cl.select(rows, "stride", ("a",))) == {"walk", "push"}
    assert cl.select(rows, "stride")["walk"]["part"] == "a"  # no parts: the first row
    assert cl.select(rows, "onn") == {}
    assert cl.parse_pick("STRIDE=stride@b,a") == ("STRIDE", "stride", ("b", "a"))
    assert cl.parse_pick("all=stride") == ("all", "stride", ())
    with pytest.raises(ValueError, match="--ref 'stride': expected LABEL=MODEL"):
        cl.parse_pick("stride", "--ref")
    png = cl.bars({"policy": cl.select(rows, "policy"), "STRIDE": picked},
                  ["walk", "push", "rough"], tmp_path / "bars.png", ylim=0.3)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    # rows written before ``seed`` existed carry their part's --seed (as the run's resume
    # reads them): two such parts run at different seeds are episodes of one model, not variants
    for name, seed in (("s0", 0), ("s3", 3)):
        _part(tmp_path / name, [_row("walk", "stride", 0.07 + seed / 100)], "c")
        data = json.loads((tmp_path / name / "closed_loop.json").read_text())
        data["env"]["config"] = dict(seed=seed)
        (tmp_path / name / "closed_loop.json").write_text(json.dumps(data))
    rows = cl.merge([str(tmp_path / "s0"), str(tmp_path / "s3")], str(tmp_path / "m2"))
    assert [r["model"] for r in rows] == ["stride", "stride"]
    # ... but draws of another planner (a flag, or the model's file, differs) are a variant even
    # at new seeds; a setting only one of them records (added since) does not count
    for name, seed, gate, path in (("g0", 0, 0.0, "m/a"), ("g4", 4, 0.0, "m/a"),
                                   ("gate", 8, 3.5, "m/a"), ("file", 9, 0.0, "m/b")):
        _part(tmp_path / name, [dict(_row("walk", "stride", 0.07), seed=seed)], "c")
        data = json.loads((tmp_path / name / "closed_loop.json").read_text())
        planning = dict(trust_limit=gate) | (dict(trust_overshoot=0.0) if seed else {})
        data["env"]["config"] = dict(seed=seed, out=f"/o/{name}", models=f"stride={path}",
                                     planning=planning)
        (tmp_path / name / "closed_loop.json").write_text(json.dumps(data))
    rows = cl.merge([str(tmp_path / n) for n in ("g0", "g4", "gate", "file")],
                    str(tmp_path / "m4"))
    assert [r["model"] for r in rows] == ["stride", "stride", "stride@gate", "stride@file"]

    # a part of several episodes (--episodes 3) whose first clashes with an earlier part's: all
    # three are the variant's, not one renamed and two left among the earlier part's model
    draws = [dict(_row("walk", "stride", 0.06 + s / 100), seed=s, episode=s) for s in range(3)]
    _part(tmp_path / "draws", draws, "d")
    rows = cl.merge([str(tmp_path / "s0"), str(tmp_path / "draws")], str(tmp_path / "m3"))
    assert [(r["model"], r.get("seed")) for r in rows] == [
        ("stride", None), ("stride@draws", 0), ("stride@draws", 1), ("stride@draws", 2)]


def test_a_merge_onto_an_earlier_one_keeps_its_rows_and_notes(tmp_path):
    """``onto``: the earlier merge's rows stay as they are (a note added to one since
    included), the new part's rows follow, renamed against the old ones; a part merged twice
    is an error."""
    a = _part(tmp_path / "a", [_row("walk", "stride", 0.07), _row("walk", "policy", 0.068)], "1")
    first = tmp_path / "first"
    cl.merge([str(a)], str(first), "t")
    data = json.loads((first / "closed_loop.json").read_text())
    data["rows"][0]["note"] = "checked by hand"
    (first / "closed_loop.json").write_text(json.dumps(data))
    b = _part(tmp_path / "b", [_row("walk", "stride", 0.05), _row("push", "stride", 0.2)], "2")
    rows = cl.merge([str(b)], str(tmp_path / "second"), onto=str(first / "closed_loop.json"))
    assert rows[:2] == data["rows"]
    assert [(r["model"], r["part"]) for r in rows[2:]] == [("stride@b", "b"), ("stride", "b")]
    back = json.loads((tmp_path / "second" / "closed_loop.json").read_text())
    assert back["title"] == "t" and set(back["parts"]) == {"a", "b"}
    with pytest.raises(ValueError, match="already merged"):
        cl.merge([str(a)], str(tmp_path / "third"), onto=str(first / "closed_loop.json"))
    # the same part grown since (its run resumed): only the new rows come, renamed as before
    data = json.loads((b / "closed_loop.json").read_text())
    data["rows"].append(_row("walk", "onn", 0.06))
    data["rows"].append(dict(_row("walk", "stride", 0.04), seed=1))
    (b / "closed_loop.json").write_text(json.dumps(data))
    again = cl.merge([str(b)], str(tmp_path / "third"),
                     onto=str(tmp_path / "second" / "closed_loop.json"))
    assert again[:4] == rows
    assert [(r["model"], r["part"]) for r in again[4:]] == [("onn", "b"), ("stride@b", "b")]
    # the headline (the current planner's parts): set, kept by a later merge onto it, refused
    # for a part the table does not hold; no parts at all re-marks the headline alone
    cl.merge([], str(tmp_path / "fourth"), onto=str(tmp_path / "third" / "closed_loop.json"),
             headline=["b"])
    fourth = json.loads((tmp_path / "fourth" / "closed_loop.json").read_text())
    assert fourth["headline"] == {"parts": ["b"]} and fourth["rows"] == again
    assert "`b`" in (tmp_path / "fourth" / "closed_loop.md").read_text()
    c = _part(tmp_path / "c", [_row("soft", "stride", 0.1)], "3")
    fifth = cl.merge([str(c)], str(tmp_path / "fifth"),
                     onto=str(tmp_path / "fourth" / "closed_loop.json"))
    assert json.loads((tmp_path / "fifth" / "closed_loop.json").read_text())["headline"] == {
        "parts": ["b"]} and fifth[-1]["part"] == "c"
    with pytest.raises(ValueError, match="'zz' is not a part of the table"):
        cl.merge([], str(tmp_path / "sixth"), onto=str(tmp_path / "fifth" / "closed_loop.json"),
                 headline=["b", "zz"])
    # some models of a part (a run's policy rows without its planner's): each must have rows
    cl.merge([], str(tmp_path / "sixth"), onto=str(tmp_path / "fifth" / "closed_loop.json"),
             headline=["c", "b:onn+stride"])
    assert json.loads((tmp_path / "sixth" / "closed_loop.json").read_text())["headline"] == {
        "parts": ["c", "b:onn+stride"]}
    # and some scenarios of a part (its others replaced by a later planner setting)
    cl.merge([], str(tmp_path / "sixth"), onto=str(tmp_path / "fifth" / "closed_loop.json"),
             headline=["c", "b/walk", "b:onn/walk"])
    for bad in ("b:policy", "b:", "b:onn+zz", "b/soft", "b/", "b:onn/walk+soft"):
        with pytest.raises(ValueError, match="has no rows|names no"):
            cl.merge([], str(tmp_path / "seventh"),
                     onto=str(tmp_path / "fifth" / "closed_loop.json"), headline=[bad])


def test_the_recovery_alarm_fires_on_the_velocity_tracking_error(go1):
    """``alarm_speed``: the planner's alarm holds while the base's velocity is further from the
    command than that (the tracking term's error); the recovery candidates' noise is per action
    entry, and the MPPI settings carry it only where there is an alarm."""
    cfg = planning_lib.PlanningConfig(alarm_speed=0.4, recovery_noise_std=0.5, noise_std=0.15)
    planning = planning_lib.make_planning(cfg, envs.config("go1"), go1, _fake_step)
    q = planning_lib.augment(jnp.asarray(go1.info.qpos0), jnp.array([1.0, 0.0, 0.0]))
    qd = jnp.zeros(go1.mj.nv)
    assert not bool(planning.alarm(q, qd.at[0].set(1.1)))  # 0.1 m/s off: quiet
    assert bool(planning.alarm(q, qd.at[0].set(0.5)))  # 0.5 m/s short of the command
    assert bool(planning.alarm(q, qd.at[0].set(1.0).at[1].set(0.6)))  # pushed sideways
    assert planning.recovery_noise == (0.5,) * 12
    m = planning_lib.mppi_config(mppi.MPPIConfig(), cfg, planning)
    assert m.alarm_noise_std == (0.5,) * 12
    quiet = planning_lib.make_planning(planning_lib.PlanningConfig(), envs.config("go1"), go1,
                                       _fake_step)
    assert quiet.alarm is None
    assert planning_lib.mppi_config(mppi.MPPIConfig(), cfg, quiet).alarm_noise_std == 0.0
    with pytest.raises(ValueError, match="alarm_speed"):
        planning_lib.PlanningConfig(alarm_speed=-1.0)
    held = dataclasses.replace(cfg, alarm_hold_s=0.3)
    planning = planning_lib.make_planning(held, envs.config("go1"), go1, _fake_step)
    assert planning.alarm_hold == round(0.3 / go1.robot.ctrl_dt)
    assert planning_lib.mppi_config(mppi.MPPIConfig(), held, planning).alarm_hold == 15
    with pytest.raises(ValueError, match="alarm_hold_s"):
        planning_lib.PlanningConfig(alarm_hold_s=-0.1)


def test_the_trust_gate_reads_the_observers_linear_estimate(go1):
    """``trust_limit``: the planner distrusts its model while the norm of the observer's linear
    acceleration estimate exceeds it (the angular entries do not count); the hold is converted
    to control steps for the MPPI settings; the gate needs the observer and a policy."""
    cfg = planning_lib.PlanningConfig(observer_gain=0.1, trust_limit=3.5, trust_hold_s=0.2)
    policy = lambda obs, key: jnp.zeros(go1.info.nu)
    planning = planning_lib.make_planning(cfg, envs.config("go1"), go1, _fake_step, policy)
    qd = jnp.zeros(go1.mj.nv)
    at = lambda dist: planning_lib.augment(jnp.asarray(go1.info.qpos0), jnp.zeros(3),
                                           disturbance=jnp.asarray(dist, jnp.float32))
    assert not bool(planning.distrust(at([2.0, 2.0, 2.0, 9.0, 9.0, 9.0]), qd))  # |lin| 3.46
    assert bool(planning.distrust(at([2.0, 2.0, 2.1, 0.0, 0.0, 0.0]), qd))  # |lin| 3.52
    assert planning.distrust_hold == round(0.2 / go1.robot.ctrl_dt)
    assert planning_lib.mppi_config(mppi.MPPIConfig(), cfg, planning).distrust_hold == 10
    # a hold in steps on the MPPI settings that the seconds would replace is refused, named
    assert planning_lib.mppi_config(mppi.MPPIConfig(distrust_hold=10), cfg, planning)
    with pytest.raises(ValueError, match="distrust_hold=25 .*trust_hold_s=0.2 s gives 10"):
        planning_lib.mppi_config(mppi.MPPIConfig(distrust_hold=25), cfg, planning)
    assert planning_lib.make_planning(planning_lib.PlanningConfig(), envs.config("go1"), go1,
                                      _fake_step, policy).distrust is None
    with pytest.raises(ValueError, match="needs a PPO policy"):
        planning_lib.make_planning(cfg, envs.config("go1"), go1, _fake_step)
    with pytest.raises(ValueError, match="observer_gain"):
        planning_lib.PlanningConfig(trust_limit=3.5)
    with pytest.raises(ValueError, match="trust_limit"):
        planning_lib.PlanningConfig(observer_gain=0.1, trust_limit=-1.0)
    # the onset delay: seconds to control steps for MPPI, as the hold; none without the gate
    assert planning.distrust_after == 0
    assert planning_lib.mppi_config(mppi.MPPIConfig(), cfg, planning).distrust_after == 0
    delayed = dataclasses.replace(cfg, trust_delay_s=0.1)
    late = planning_lib.make_planning(delayed, envs.config("go1"), go1, _fake_step, policy)
    assert late.distrust_after == round(0.1 / go1.robot.ctrl_dt) == 5
    assert planning_lib.mppi_config(mppi.MPPIConfig(), delayed, late).distrust_after == 5
    with pytest.raises(ValueError, match="distrust_after=3 .*trust_delay_s=0.1 s gives 5"):
        planning_lib.mppi_config(mppi.MPPIConfig(distrust_after=3), delayed, late)
    with pytest.raises(ValueError, match="trust_delay_s=0.1 delays the model-trust gate"):
        planning_lib.PlanningConfig(trust_delay_s=0.1)
    # with latency the planner steps once per replanning period: the holds and the delay count
    # those (1 s of hold at 2 periods per plan: 25 planner steps, 50 control periods)
    slow = dataclasses.replace(delayed, trust_hold_s=1.0, alarm_speed=0.5, alarm_hold_s=0.4,
                               latency_s=1.5 * go1.robot.ctrl_dt)
    late = planning_lib.make_planning(slow, envs.config("go1"), go1, _fake_step, policy)
    assert late.latency_steps == 2
    assert (late.distrust_hold, late.distrust_after, late.alarm_hold) == (25, 2, 10)
    with pytest.raises(ValueError, match="trust_delay_s=-0.1 must be >= 0"):
        planning_lib.PlanningConfig(observer_gain=0.1, trust_limit=3.5, trust_delay_s=-0.1)


def test_the_trust_gate_can_read_the_downward_estimate_alone(go1):
    """``trust_component="down"``: the gate reads the estimate's downward entry alone (a model
    predicting the base higher than it goes), blind to floor-plane and upward errors the norm
    would count; an unknown component is named."""
    cfg = planning_lib.PlanningConfig(observer_gain=0.1, trust_limit=2.5, trust_component="down")
    policy = lambda obs, key: jnp.zeros(go1.info.nu)
    planning = planning_lib.make_planning(cfg, envs.config("go1"), go1, _fake_step, policy)
    norm = planning_lib.make_planning(dataclasses.replace(cfg, trust_component="norm"),
                                      envs.config("go1"), go1, _fake_step, policy)
    qd = jnp.zeros(go1.mj.nv)
    at = lambda dist: planning_lib.augment(jnp.asarray(go1.info.qpos0), jnp.zeros(3),
                                           disturbance=jnp.asarray(dist, jnp.float32))
    for dist, down, by_norm in (([0.0, 0.0, -2.6, 0, 0, 0], True, True),  # down past the limit
                                ([3.0, 0.0, 0.0, 0, 0, 0], False, True),  # a push: the floor plane
                                ([0.0, 0.0, 2.6, 0, 0, 0], False, True),  # upward
                                ([1.5, 1.5, -2.4, 0, 0, 0], False, True),  # |lin| 3.2, down 2.4
                                ([0.0, 0.0, -2.4, 0, 0, 9.0], False, False)):  # angular: not read
        assert bool(planning.distrust(at(dist), qd)) is down, dist
        assert bool(norm.distrust(at(dist), qd)) is by_norm, dist
    with pytest.raises(ValueError, match="trust_component='up': one of norm, down"):
        planning_lib.PlanningConfig(trust_component="up")


def test_the_stop_prior_prices_the_familys_offsets_at_a_stop_command_only(go1):
    """``family_cost_stop``: the offsets' prior the planning hands MPPI is the full cost at a
    stop command and fades with the command's size (``stop_speed``); it needs the policy
    family, and bad settings are named."""
    policy = lambda obs, key: jnp.zeros(go1.info.nu)
    cfg = planning_lib.PlanningConfig(family_cost_stop=0.3, stop_speed=0.1)
    planning = planning_lib.make_planning(cfg, envs.config("go1"), go1, _fake_step, policy)
    q0, qd = jnp.asarray(go1.info.qpos0), jnp.zeros(go1.mj.nv)
    at = lambda cmd: float(planning.family_prior(planning_lib.augment(q0, jnp.asarray(cmd)), qd))
    assert at([0.0, 0.0, 0.0]) == pytest.approx(0.3)
    assert at([0.05, 0.0, 0.0]) == pytest.approx(0.3 * np.exp(-0.25), rel=1e-5)
    assert at([1.0, 0.0, 0.0]) < 1e-30 and at([0.0, 0.0, 0.5]) < 1e-9  # walking or turning
    assert planning_lib.make_planning(planning_lib.PlanningConfig(), envs.config("go1"), go1,
                                      _fake_step, policy).family_prior is None
    with pytest.raises(ValueError, match="family_cost_stop=0.3 .*needs a PPO policy"):
        planning_lib.make_planning(cfg, envs.config("go1"), go1, _fake_step)
    with pytest.raises(ValueError, match="stop_speed=0"):
        planning_lib.PlanningConfig(family_cost_stop=0.3, stop_speed=0.0)


def test_the_trust_gate_also_reads_a_forward_overshoot_of_the_command(go1):
    """``trust_overshoot``: the policy also acts while the base's forward velocity (base frame)
    exceeds the commanded one by more than it; with both triggers either one holds the gate;
    alone it needs no observer, but a policy; the run's summary names what trips the gate."""
    from stride_jax.jobs import closed_loop as cl
    policy = lambda obs, key: jnp.zeros(go1.info.nu)
    q0 = jnp.asarray(go1.info.qpos0)
    yaw90 = q0.at[3:7].set(jnp.array([np.cos(np.pi / 4), 0.0, 0.0, np.sin(np.pi / 4)]))

    def state(vx_world, vy_world=0.0, q=q0, dist=(0.0,) * 6):
        q_aug = planning_lib.augment(q, jnp.array([1.0, 0.0, 0.0]),
                                     disturbance=jnp.asarray(dist, jnp.float32))
        return q_aug, jnp.zeros(go1.mj.nv).at[0].set(vx_world).at[1].set(vy_world)

    over = planning_lib.make_planning(planning_lib.PlanningConfig(trust_overshoot=0.15),
                                      envs.config("go1"), go1, _fake_step, policy)
    assert not bool(over.distrust(*state(1.14)))
    assert bool(over.distrust(*state(1.16)))
    assert not bool(over.distrust(*state(0.0)))  # behind the command: the tracking's business
    # the base frame: turned 90 degrees, the world's y velocity is the forward one
    assert bool(over.distrust(*state(0.0, 1.2, q=yaw90)))
    assert not bool(over.distrust(*state(1.2, 0.0, q=yaw90)))
    both = planning_lib.make_planning(
        planning_lib.PlanningConfig(observer_gain=0.1, trust_limit=3.5, trust_overshoot=0.15),
        envs.config("go1"), go1, _fake_step, policy)
    assert bool(both.distrust(*state(1.2)))
    assert bool(both.distrust(*state(1.0, dist=(4.0, 0.0, 0.0, 0.0, 0.0, 0.0))))
    assert not bool(both.distrust(*state(1.0, dist=(3.0, 0.0, 0.0, 0.0, 0.0, 0.0))))
    with pytest.raises(ValueError, match="trust_overshoot=0.15 hands control to the policy"):
        planning_lib.make_planning(planning_lib.PlanningConfig(trust_overshoot=0.15),
                                   envs.config("go1"), go1, _fake_step)
    with pytest.raises(ValueError, match="trust_overshoot=-0.1"):
        planning_lib.PlanningConfig(trust_overshoot=-0.1)
    assert cl._gate_words(planning_lib.PlanningConfig(
        observer_gain=0.1, trust_limit=3.5, trust_overshoot=0.15)) == (
        "the observer's linear estimate exceeds 3.5 m/s^2 or the forward velocity exceeds the "
        "command by 0.15 m/s")


def test_model_precision_reaches_the_learned_models_products():
    """``model_precision``: the learned step's matrix products carry the asked precision in the
    lowered program (a CPU computes float32 either way; a GPU's default is TF32); JAX's default
    leaves them unmarked; an unknown name is a clear error."""
    from stride_jax.dynamics import checkpoint
    model, params = checkpoint.load("results/models/go1_walk/onn-s0")
    q = jnp.zeros(model.spec.nq).at[3].set(1.0)
    args = (q, jnp.zeros(model.spec.nv), jnp.zeros(12), jax.random.key(0))
    text = {p: jax.jit(cl.learned_step(model, params, p)).lower(*args).as_text()
            for p in ("", "highest")}
    assert "HIGHEST" in text["highest"] and "HIGHEST" not in text[""]
    with pytest.raises(ValueError, match="--model-precision is 'tf32'"):
        cl.ClosedLoopConfig(model_precision="tf32")
    with pytest.raises(ValueError, match="precision 'x'"):
        cl.learned_step(model, params, "x")


def test_the_policy_episode_records_each_period_and_its_true_next_state(go1):
    """``episode.policy_episode``: the policy alone in a scenario; each period's recorded next
    state is the next period's state, and its joint targets are the policy's action through the
    planning's ``ctrl``. A planning without a policy is refused."""
    from stride_jax.control import episode as episode_lib
    sc = dataclasses.replace(cl.SCENARIOS["walk"], seconds=4 * go1.robot.ctrl_dt)
    world = cl.scenario_world(go1, sc)
    planning = planning_lib.make_planning(planning_lib.PlanningConfig(), envs.config("go1"), go1,
                                          cl.mjx_step_fn(go1, world.mx))
    nq = go1.mj.nq
    planning = planning._replace(policy=lambda q, qd: jnp.asarray(planning.nominal_u) + 0.1 * q[nq])
    ep = jax.device_get(episode_lib.policy_episode(world, planning))
    assert ep.q_aug.shape == (4, nq + planning_lib.N_AUG) and ep.fallen.shape == (4,)
    np.testing.assert_allclose(ep.t, np.arange(4) * go1.robot.ctrl_dt, rtol=1e-6)
    np.testing.assert_array_equal(ep.q_next[:-1], ep.q_aug[1:, :nq])
    np.testing.assert_array_equal(ep.qd_next[:-1], ep.qd[1:])
    np.testing.assert_allclose(ep.ctrl, jax.vmap(planning.ctrl)(ep.q_aug, ep.u), atol=1e-6)
    assert not np.allclose(ep.q_next[-1], ep.q_aug[0, :nq])  # the robot moved
    with pytest.raises(ValueError, match="needs a planning with a policy"):
        episode_lib.policy_episode(world, planning._replace(policy=None))


def test_the_policy_alone_reads_its_run_and_governs_the_commands(go1, monkeypatch):
    """``episode.policy_alone``: the run's policy and task settings in the scenario's world; with
    ``govern`` the commands it sees are clipped to the task's range (as the closed loop's
    ``--govern``), without it they are the scenario's."""
    from stride_jax.control import episode as episode_lib, ppo
    env_cfg = envs.config("go1")
    read = []
    monkeypatch.setattr(ppo, "load_policy", lambda run: read.append(run) or (
        lambda obs, key: jnp.zeros(go1.info.nu), None, env_cfg))
    sc = scenarios.Scenario("fast", ((0.0, 9.0, 0.0, 0.0),), seconds=3 * go1.robot.ctrl_dt)
    ep, cfg = episode_lib.policy_alone(go1, sc, "some/run", govern=True)
    assert read == ["some/run"] and cfg is env_cfg
    nq = go1.mj.nq
    seen = np.asarray(jax.vmap(lambda qa: planning_lib.split(qa, nq).command)(ep.q_aug))
    hi = np.asarray(env_cfg.commands.bounds()[1])
    np.testing.assert_allclose(seen, np.tile([hi[0], 0.0, 0.0], (3, 1)), atol=1e-6)
    assert hi[0] < 9.0 and ep.fallen.shape == (3,)
    assert scenarios.governed(sc, env_cfg.commands.bounds()).commands[0][1] == hi[0]


def _sensing_planning(go1):
    """Planning through MJX whose policy acts its observed gravity: the first three actions are
    the observation's gravity entries."""
    nu = go1.info.nu
    return planning_lib.make_planning(
        planning_lib.PlanningConfig(), envs.config("go1"), go1,
        cl.mjx_step_fn(go1, mjx.put_model(go1.mj)),
        ppo_policy=lambda obs, key: jnp.zeros(nu).at[:3].set(obs[6:9]))


def test_the_controller_senses_the_scenarios_gravity(go1):
    """A slope emulated by tilting gravity under a level floor: an IMU on a real slope reads the
    slope, so the policy and the planner observe the simulation's gravity direction (before
    session 46 they read world down, which hid the slope). A base pitched with the tilted
    gravity reads upright; on flat ground the controller's state is unchanged bit for bit; a run
    that kept no such setting merges as world down."""
    from stride_jax.control import episode as episode_lib
    th = np.deg2rad(15.0)
    g_hat = jnp.array([-np.sin(th), 0.0, -np.cos(th)], jnp.float32)
    q = jnp.asarray(go1.info.qpos0).at[3:7].set(jnp.array([np.cos(th / 2), 0, np.sin(th / 2), 0]))
    qd = jnp.zeros(go1.mj.nv)
    np.testing.assert_allclose(envs.base_signals(q, qd, g_hat)[2], [0, 0, -1], atol=1e-6)
    np.testing.assert_allclose(envs.base_signals(q, qd)[2], [np.sin(th), 0, -np.cos(th)],
                               atol=1e-6)  # world down: the base reads pitched
    # the planning's policy and cost see the gravity carried in the planner's state
    nu = go1.info.nu
    env_cfg = envs.config("go1")
    planning = _sensing_planning(go1)
    policy, dynamics = jax.jit(planning.policy), jax.jit(planning.dynamics)  # one MJX compile,
    for g, seen in ((g_hat, [0, 0, -1]), (None, [np.sin(th), 0, -np.cos(th)])):  # not op by op
        q_aug = planning_lib.augment(q, jnp.zeros(3), gravity=g)
        np.testing.assert_allclose(policy(q_aug, qd)[:3],
                                   env_cfg.action_scale * np.asarray(seen), atol=1e-6)
        nxt, _ = dynamics(q_aug, qd, jnp.zeros(nu), jax.random.key(0))
        np.testing.assert_array_equal(planning_lib.split(nxt, go1.mj.nq).gravity,
                                      planning_lib.split(q_aug, go1.mj.nq).gravity)  # held
    # the episode hands the scenario's gravity to the controller, or world down when told not to
    nq = go1.mj.nq
    slope = dataclasses.replace(cl.SCENARIOS["slope"], seconds=3 * go1.robot.ctrl_dt,
                                slope_deg=15.0)
    w = cl.scenario_world(go1, slope)
    on, off = (jax.device_get(episode_lib.policy_episode(w, planning, sense))
               for sense in (True, False))
    np.testing.assert_allclose(on.q_aug[:, nq + planning_lib.N_AUG - 3:],
                               np.tile(g_hat, (3, 1)), atol=1e-6)
    np.testing.assert_array_equal(off.q_aug[:, nq + planning_lib.N_AUG - 3:],
                                  np.tile([0, 0, -1], (3, 1)))
    assert not np.allclose(on.u, off.u)
    # flat ground: the sensed gravity is world down to the bit, so the controller's state is
    # the one it had before sensing (both episodes' code paths meet at augment)
    flat = cl.scenario_world(go1, dataclasses.replace(cl.SCENARIOS["walk"],
                                                      seconds=3 * go1.robot.ctrl_dt))
    for t in (0.0, 0.02, 5.0):
        sensed = episode_lib.sensed_gravity(flat.mx, jnp.float32(t), flat.tilt)
        np.testing.assert_array_equal(planning_lib.augment(q, jnp.zeros(3), gravity=sensed),
                                      planning_lib.augment(q, jnp.zeros(3)))
    # merging: a run without the key ran with world down
    old = {"config": {"robot": "go1"}}
    new = {"config": {"robot": "go1", "sense_gravity": True}}
    assert not cl._same_settings(cl._settings(old, "stride"), cl._settings(new, "stride"))
    assert cl._same_settings(cl._settings(old, "stride"),
                             cl._settings({"config": {"robot": "go1", "sense_gravity": False}},
                                          "stride"))


@pytest.mark.slow  # the policy's episode senses the slope: test_the_controller_senses_the_scenarios_gravity
def test_the_closed_loops_episode_senses_as_the_policy_episode_does(go1):
    """The closed loop's episode (no planner: the policy acting) gives the policy episode's actions
    on a sensed slope, and a recorded step's next state carries the gravity sensed at its time."""
    from stride_jax.control import episode as episode_lib
    planning = _sensing_planning(go1)
    nq, nu = go1.mj.nq, go1.info.nu
    slope = dataclasses.replace(cl.SCENARIOS["slope"], seconds=3 * go1.robot.ctrl_dt,
                                slope_deg=15.0)
    w = cl.scenario_world(go1, slope)
    on = jax.device_get(episode_lib.policy_episode(w, planning, True))
    act = jax.device_get(cl.run_episode(w.sm, w.mx, w.slots, planning, None, 3, w.starts,
                                        w.values, jax.random.key(0), tilt=w.tilt)).action
    np.testing.assert_allclose(act, on.u, atol=1e-6)  # the closed loop's episode: the same
    # a recorded step's next state carries the gravity sensed at its time (a tilting ground)
    tilt = dataclasses.replace(cl.SCENARIOS["tilt"], seconds=3 * go1.robot.ctrl_dt)
    wt = cl.scenario_world(go1, tilt)
    grav = lambda qa: planning_lib.split(qa, nq).gravity

    def step(state, q_aug, qd):  # a one-step "planner": the policy's action
        u, z = planning.policy(q_aug, qd), jnp.zeros(1)
        return u, state, mppi.Info(z, z, z[0], u[None], jnp.zeros((), jnp.int32), u[None, None],
                                   z, jnp.ones(1, jnp.int32), jnp.zeros((), bool))

    acting = mppi.Planner(lambda key, plan=None: mppi.MPPIState(jnp.zeros((1, nu)), key), step)
    _, (now, nxt) = jax.device_get(cl.run_episode(
        wt.sm, wt.mx, wt.slots, planning, acting, 3, wt.starts, wt.values, jax.random.key(0),
        tilt=wt.tilt, record=lambda qa, qd, u, info, qa2, *_: (grav(qa), grav(qa2))))
    assert not np.allclose(now[1], now[0])  # the ground tilts step by step
    np.testing.assert_allclose(nxt[:-1], now[1:], atol=1e-7)
    # record_every: the same records at every other step (from the first), zeros between
    _, (now2, _) = jax.device_get(cl.run_episode(
        wt.sm, wt.mx, wt.slots, planning, acting, 3, wt.starts, wt.values, jax.random.key(0),
        tilt=wt.tilt, record=lambda qa, qd, u, info, qa2, *_: (grav(qa), grav(qa2)),
        record_every=2))
    np.testing.assert_allclose(now2[::2], now[::2], atol=1e-7)
    assert not now2[1].any()
    with pytest.raises(ValueError, match="record_every"):
        cl.run_episode(wt.sm, wt.mx, wt.slots, planning, acting, 3, wt.starts, wt.values,
                       jax.random.key(0), record=lambda *a: a[0], record_every=0)


def test_the_velocity_integral_moves_the_planners_command_against_a_steady_error():
    """``velocity_integral``: a steady overshoot integrates (after the settle time) into a lower
    command, bounded by the limit; a command change resets it; the yaw rate is left alone; bad
    settings are named."""
    planning = planning_lib.Planning(*[None] * 9)._replace(
        velocity_integral=2.0, velocity_integral_limit=0.1, velocity_integral_settle_s=0.11)
    dt, command = 0.02, jnp.array([1.0, 0.0, 0.3])
    integral, since, prev = jnp.zeros(2), jnp.zeros(()), jnp.full(3, jnp.nan)
    v = jnp.array([1.05, -0.02, 0.0])  # 0.05 m/s too fast, 0.02 m/s drifting right
    shifts = []
    for _ in range(100):
        integral, since = planning_lib.integrate_velocity_error(planning, integral, since,
                                                                command, prev, v, dt)
        prev = command
        shifts.append(planning_lib.integral_command(planning, command, integral))
    # nothing in the settle time (0.11 s: 5 periods), then 2/s x 0.05 m/s x the time since
    np.testing.assert_allclose(shifts[3], command, atol=1e-7)
    np.testing.assert_allclose(shifts[20][:2], [1.0 - 2 * 0.05 * 0.32, 2 * 0.02 * 0.32], atol=1e-5)
    assert float(shifts[-1][0]) == pytest.approx(0.9, abs=1e-6)  # the limit: 0.1 m/s
    assert float(shifts[-1][2]) == pytest.approx(0.3)  # the yaw rate as commanded
    integral, since = planning_lib.integrate_velocity_error(planning, integral, since,
                                                            jnp.array([0.5, 0.0, 0.0]), prev, v, dt)
    assert float(jnp.abs(integral).max()) == 0.0 and float(since) == pytest.approx(dt)
    with pytest.raises(ValueError, match="velocity_integral=-1"):
        planning_lib.PlanningConfig(velocity_integral=-1.0)
    with pytest.raises(ValueError, match="velocity_integral_band=-0.1"):
        planning_lib.PlanningConfig(velocity_integral_band=-0.1)


def test_the_velocity_integrals_band_leaves_a_transient_out():
    """``velocity_integral_band``: an axis's error beyond the band (an acceleration from rest,
    a push) leaves that axis's integral as it is, one within it integrates as without a band."""
    planning = planning_lib.Planning(*[None] * 9)._replace(
        velocity_integral=1.0, velocity_integral_limit=0.2, velocity_integral_settle_s=0.0,
        velocity_integral_band=0.1)
    dt, command = 0.02, jnp.array([1.0, 0.0, 0.0])
    integral, since = jnp.zeros(2), jnp.zeros(())
    for v_x in (0.3, 0.5, 0.7, 0.85):  # accelerating: 0.7 .. 0.15 m/s below the command
        integral, since = planning_lib.integrate_velocity_error(
            planning, integral, since, command, command, jnp.array([v_x, 0.05, 0.0]), dt)
    # forward: nothing entered; lateral: 0.05 m/s, within the band, every period
    np.testing.assert_allclose(integral, [0.0, 4 * 0.05 * dt], atol=1e-7)
    integral, since = planning_lib.integrate_velocity_error(
        planning, integral, since, command, command, jnp.array([0.95, 0.05, 0.0]), dt)
    np.testing.assert_allclose(integral, [-0.05 * dt, 5 * 0.05 * dt], atol=1e-7)
    unbanded = planning._replace(velocity_integral_band=0.0)
    grown, _ = planning_lib.integrate_velocity_error(
        unbanded, jnp.zeros(2), since, command, command, jnp.array([0.3, 0.0, 0.0]), dt)
    np.testing.assert_allclose(grown, [-0.7 * dt, 0.0], atol=1e-7)



def _standing_planner(sm) -> mppi.Planner:
    """A one-step stand-in for a planner: it holds the home pose, so a test sees what the
    closed loop around it does (the command it is asked, the trace) without a plan's work."""
    nu = sm.info.nu

    def step(state, q_aug, qd):
        u, z = jnp.asarray(sm.info.qpos0[7:]), jnp.zeros(1)
        return u, state, mppi.Info(z, z, z[0], u[None], jnp.zeros((), jnp.int32), u[None, None],
                                   z, jnp.ones(1, jnp.int32), jnp.zeros((), bool))

    return mppi.Planner(lambda key, plan=None: mppi.MPPIState(jnp.zeros((1, nu)), key), step)


def test_the_overspeed_guard_lowers_the_speed_asked_past_the_command_only():
    """``overspeed_gain``: speed along the command past it plus the margin integrates into a
    lower speed asked, along the command's own direction, bounded by the limit and never past a
    stop; it drains where the robot is slower and never asks for more than the command; a stop
    command is not guarded; the yaw rate is left alone; bad settings are named."""
    planning = planning_lib.Planning(*[None] * 9)._replace(
        overspeed_gain=2.0, overspeed_margin=0.1, overspeed_limit=0.3)
    dt, command = 0.02, jnp.array([0.6, 0.8, 0.3])  # 1 m/s, diagonal
    over = jnp.zeros(())
    v = jnp.array([0.6, 0.8, 0.0]) * 1.25 + jnp.array([0.4, -0.3, 0.0])  # 0.25 m/s past, + across
    for _ in range(10):
        over = planning_lib.integrate_overspeed(planning, over, command, v, dt)
    assert float(over) == pytest.approx(10 * 0.15 * dt, abs=1e-6)  # past the margin: 0.15 m/s
    asked = planning_lib.overspeed_command(planning, command, over)
    np.testing.assert_allclose(asked[:2], (1.0 - 2.0 * 0.03) * command[:2], atol=1e-6)
    assert float(asked[2]) == pytest.approx(0.3)  # the yaw rate as commanded
    for _ in range(200):  # held at the limit: 0.3 m/s off
        over = planning_lib.integrate_overspeed(planning, over, command, v, dt)
    asked = planning_lib.overspeed_command(planning, command, over)
    assert float(jnp.linalg.norm(asked[:2])) == pytest.approx(0.7, abs=1e-6)
    slow = jnp.array([0.3, 0.4, 0.0])  # 0.5 m/s: 0.6 short of the command plus the margin
    drained = planning_lib.integrate_overspeed(planning, over, command, slow, dt)
    assert float(drained) == pytest.approx(float(over) - 0.6 * dt, abs=1e-6)
    for _ in range(50):  # never below 0: never more than the command asked
        drained = planning_lib.integrate_overspeed(planning, drained, command, slow, dt)
    assert float(drained) == 0.0
    np.testing.assert_allclose(planning_lib.overspeed_command(planning, command, drained), command)
    stop = jnp.array([0.0, 0.0, 0.5])  # no direction: not guarded, the integral kept
    assert float(planning_lib.integrate_overspeed(planning, over, stop, v, dt)) == float(over)
    np.testing.assert_allclose(planning_lib.overspeed_command(planning, stop, over), stop)
    big = planning._replace(overspeed_limit=5.0)  # a cut past the speed stops, never reverses
    np.testing.assert_allclose(planning_lib.overspeed_command(big, command, jnp.asarray(2.0)),
                               [0.0, 0.0, 0.3], atol=1e-7)
    with pytest.raises(ValueError, match="overspeed_gain=-1"):
        planning_lib.PlanningConfig(overspeed_gain=-1.0)


def test_the_closed_loop_guards_the_speed_asked_after_a_push_forward(go1):
    """In the episode the overspeed guard runs around whichever controller acts: pushed forward
    past a slow command, the planner (here a stand-still stand-in) is asked for less speed the
    periods after, never more than the command, while the trace keeps the scenario's command;
    off, the planner sees the command itself."""
    nq = go1.mj.nq
    mx = mjx.put_model(go1.mj)
    walk = dataclasses.replace(cl.SCENARIOS["walk"], seconds=12 * go1.robot.ctrl_dt)
    w = cl.scenario_world(go1, walk)
    starts, values = jnp.zeros(1), jnp.array([[0.2, 0.0, 0.0]])
    mass = float(np.sum(go1.mj.body_mass))
    pushes = jnp.array([[0.0, 0.1, mass * 1.5 / 0.1, 0.0]] + [[0.0] * 4] * 3)  # +1.5 m/s forward

    standing = _standing_planner(go1)
    seen = {}
    for gain in (0.0, 5.0):
        planning = planning_lib.make_planning(
            planning_lib.PlanningConfig(overspeed_gain=gain), envs.config("go1"), go1,
            cl.mjx_step_fn(go1, mx))
        trace, cmd = jax.device_get(cl.run_episode(
            w.sm, w.mx, w.slots, planning, standing, 12, starts, values, jax.random.key(0),
            pushes=pushes, record=lambda qa, *_: planning_lib.split(qa, nq).command))
        np.testing.assert_allclose(trace.command, np.tile([0.2, 0.0, 0.0], (12, 1)))
        seen[gain] = (cmd, trace.v_base)
    np.testing.assert_allclose(seen[0.0][0], np.tile([0.2, 0.0, 0.0], (12, 1)))
    cmd, v = seen[5.0]
    assert v[:5, 0].max() > 0.5  # the push took the robot well past the command
    assert cmd[0, 0] == pytest.approx(0.2) and cmd[-1, 0] < 0.2 - 1e-3  # asked for less after
    assert (cmd[:, 0] <= 0.2 + 1e-7).all() and (cmd[:, 0] >= 0).all() and (cmd[:, 1:] == 0).all()


def test_the_closed_loop_plans_to_the_integral_command_and_scores_the_true_one(go1):
    """In the episode the planner's state carries the shifted command once the settle time has
    passed (a robot standing still is below a 1 m/s command: the shift is upward), while the
    trace keeps the scenario's command; off, the planner sees the command itself."""
    nq = go1.mj.nq
    mx = mjx.put_model(go1.mj)
    walk = dataclasses.replace(cl.SCENARIOS["walk"], seconds=8 * go1.robot.ctrl_dt)
    w = cl.scenario_world(go1, walk)

    standing = _standing_planner(go1)
    seen = {}
    for ki in (0.0, 1.0):
        planning = planning_lib.make_planning(
            planning_lib.PlanningConfig(velocity_integral=ki, velocity_integral_settle_s=0.05),
            envs.config("go1"), go1, cl.mjx_step_fn(go1, mx))
        trace, cmd = jax.device_get(cl.run_episode(
            w.sm, w.mx, w.slots, planning, standing, 8, w.starts, w.values, jax.random.key(0),
            record=lambda qa, *_: planning_lib.split(qa, nq).command))
        np.testing.assert_array_equal(trace.command, np.tile([1.0, 0.0, 0.0], (8, 1)))
        seen[ki] = cmd
    np.testing.assert_array_equal(seen[0.0], np.tile([1.0, 0.0, 0.0], (8, 1)))
    np.testing.assert_array_equal(seen[1.0][:3], seen[0.0][:3])  # within the settle time
    assert (np.diff(seen[1.0][3:, 0]) > 0).all() and (seen[1.0][3:, 2] == 0).all()


def test_latency_auto_runs_each_planner_late_by_its_own_measured_time(tmp_path):
    """``--latency-auto``: each planner's controller is timed on time first and its plans then
    act that many control periods late (``latency_auto_ms`` -> ``latency_steps``, rounded up);
    the policy needs no planning time; it refuses a fixed latency beside it."""
    cfg = dataclasses.replace(cl.PRESETS["tiny"], seconds=0.1, latency_auto=True,
                              models="stride=results/models/go1/stride-s0,policy",
                              policy="results/policies/ppo_go1", controller_repeats=3,
                              out=str(tmp_path))
    rows = {r["model"]: r for r in cl.run(cfg, log=lambda *_: None)}
    late = rows["stride"]
    assert late["latency_auto_ms"] > 0
    assert late["latency_steps"] == planning_lib.latency_steps(
        planning_lib.PlanningConfig(latency_s=late["latency_auto_ms"] / 1e3), 0.02) >= 1
    assert rows["policy"]["latency_steps"] is None and "latency_auto_ms" not in rows["policy"]
    with pytest.raises(ValueError, match="--latency-auto .* no --planning.latency-s"):
        dataclasses.replace(cfg, planning=planning_lib.PlanningConfig(latency_s=0.04))
