"""Velocity-command MJX environments: shapes under jit, finite rewards, fresh resets, rewards that
favour tracking, and the observation a planner rebuilds from (q, qd, command)."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from stride_jax.control import envs, scenarios, wrappers


@pytest.fixture(scope="module")
def go1_env(go1):
    return envs.make("go1")


def test_go1_env_runs_jitted_with_fresh_resets(go1_env):
    env = go1_env
    n_envs, n_steps, episode = 2, 4, 3
    wrapped = wrappers.wrap_for_training(env, episode_length=episode)

    def run(key):
        s0 = wrapped.reset(jax.random.key_data(jax.random.split(key, n_envs)))

        def body(s, _):
            s = wrapped.step(s, jnp.zeros((n_envs, env.action_size)))
            return s, (s.obs, s.reward, s.done, s.info["command"], s.info["t"],
                       s.pipeline_state.qpos, s.pipeline_state.qvel)

        return s0, jax.lax.scan(body, s0, None, length=n_steps)

    key = jax.random.key(0)
    # XLA's backend optimisations cost a third of the compile time and buy nothing in 4 steps.
    compiled = jax.jit(run).lower(key).compile({"xla_backend_optimization_level": 0})
    s0, (s_end, (obs, reward, done, cmd, t, q, qd)) = compiled(key)
    assert s0.obs.shape == (n_envs, env.observation_size) == (n_envs, 12 + 2 * 12)
    assert obs.shape == (n_steps, n_envs, env.observation_size)
    assert np.isfinite(obs).all() and np.isfinite(reward).all()
    assert (reward >= 0).all()  # rewards are clipped at zero
    assert set(s_end.metrics) >= {"reward/tracking_lin_vel", "reward/orientation", "fallen"}
    # Holding the home pose keeps it standing: no falls, base above the fall height.
    assert not done[:episode - 1].any()
    assert (q[..., 2] > go1_env.sm.robot.min_base_height).all()
    # The episode ends at its length; the next step starts a fresh episode with a new command.
    assert done[episode - 1].all()
    np.testing.assert_array_equal(t[episode - 1], 0)
    assert not np.allclose(cmd[episode - 1], cmd[episode - 2])
    # The observation is a function of (q, qd, command) alone: a planner can rebuild it.
    obs_fn = jax.vmap(env.observation_fn())
    np.testing.assert_allclose(obs_fn(q[1], qd[1], cmd[1]), obs[1], atol=1e-5)


def _state(vx=0.0, yaw_rate=0.0, tilt=0.0, home=None):
    """A Go1-sized floating-base state moving at ``vx`` (world x, heading along x)."""
    q = jnp.concatenate([jnp.array([0.0, 0.0, 0.3, jnp.cos(tilt / 2), jnp.sin(tilt / 2), 0, 0]),
                         home])
    qd = jnp.zeros(18).at[0].set(vx).at[5].set(yaw_rate)
    return q, qd


def test_reward_terms_favour_tracking_and_penalise_tilt(go1_env):
    cfg, home = go1_env.cfg, go1_env.home
    command = jnp.array([1.5, 0.0, 0.5])
    tau = jnp.zeros(12)
    total = lambda q, qd: envs.total_reward(cfg, envs.state_terms(
        cfg, home, q, qd, command, tau, jnp.array(False)), 0.02)[0]
    on_track = _state(1.5, 0.5, home=home)
    standing = _state(0.0, 0.0, home=home)
    tilted = _state(1.5, 0.5, tilt=0.4, home=home)
    t_on = envs.state_terms(cfg, home, *on_track, command, tau, jnp.array(False))
    t_still = envs.state_terms(cfg, home, *standing, command, tau, jnp.array(False))
    np.testing.assert_allclose(t_on["tracking_lin_vel"], 1.0, rtol=1e-6)
    np.testing.assert_allclose(t_on["tracking_ang_vel"], 1.0, rtol=1e-6)
    assert t_still["tracking_lin_vel"] < 0.5 * t_on["tracking_lin_vel"]
    assert total(*on_track) > total(*standing)
    assert total(*on_track) > total(*tilted)
    # A velocity in the world frame is tracked in the base frame: heading 90 degrees left,
    # world +y motion is forward.
    q, qd = on_track
    yaw = jnp.pi / 2
    q = q.at[3:7].set(jnp.array([jnp.cos(yaw / 2), 0, 0, jnp.sin(yaw / 2)]))
    qd = qd.at[0].set(0.0).at[1].set(1.5)
    turned = envs.state_terms(cfg, home, q, qd, command, tau, jnp.array(False))
    np.testing.assert_allclose(turned["tracking_lin_vel"], 1.0, rtol=1e-5)


def test_g1_env_shapes_and_clock(g1):
    env = envs.make("g1")
    state = jax.eval_shape(env.reset, jax.random.key_data(jax.random.key(0)))
    nxt = jax.eval_shape(env.step, state, jnp.zeros(env.action_size))
    assert env.action_size == 29
    assert state.obs.shape == nxt.obs.shape == (env.observation_size,) == (12 + 2 * 29 + 2,)
    with pytest.raises(ValueError, match="clock"):
        env.observation_fn()(jnp.zeros(36), jnp.zeros(35), jnp.zeros(3))


def test_bad_configs_are_clear_errors():
    with pytest.raises(ValueError, match="action_scale"):
        envs.config("go1", action_scale=0.0)
    with pytest.raises(ValueError, match="forward"):
        envs.config("go1", commands=envs.Commands(forward=(1.0, 0.0)))
    with pytest.raises(ValueError, match="no environment"):
        envs.config("pendulum")
    bad = dataclasses.replace(envs.PRESETS["go1"])
    with pytest.raises(ValueError, match="without a scale"):
        envs.total_reward(bad, {"not_a_term": jnp.ones(())}, 0.02)


def test_domain_randomisation_draws_friction_and_perturbs_the_targets(g1, go1):
    """``friction_min``/``max`` (``softness_min``/``max``): each reset draws the episode's
    friction (softness) factor in the range (1 without randomisation), and
    :func:`envs.with_ground` scales the model's friction (softness) as the closed loop's
    low-friction (soft) scenario does (G1's contact pairs included), and both at once; ``action_noise``: the same
    state and action step to different states under different keys."""
    from mujoco import mjx

    from stride_jax.control.scenarios import WALK, Scenario, scenario_model

    for sm in (g1, go1):
        low = scenario_model(sm, Scenario("low", WALK, friction=0.3))
        mx = envs.with_ground(mjx.put_model(sm.mj), friction=0.3)
        np.testing.assert_allclose(mx.geom_friction, low.geom_friction, rtol=1e-6)
        np.testing.assert_allclose(mx.pair_friction, low.pair_friction, rtol=1e-6)
        soft = scenario_model(sm, Scenario("soft", WALK, softness=4.0))
        mx = envs.with_ground(mjx.put_model(sm.mj), softness=4.0)
        np.testing.assert_allclose(mx.geom_solref, soft.geom_solref, rtol=1e-6)
        np.testing.assert_allclose(mx.pair_solref, soft.pair_solref, rtol=1e-6)
        assert not np.allclose(soft.geom_solref, sm.mj.geom_solref)
        both = envs.with_ground(mjx.put_model(sm.mj), friction=0.3, softness=4.0)
        np.testing.assert_allclose(both.pair_friction, low.pair_friction, rtol=1e-6)
        np.testing.assert_allclose(both.pair_solref, soft.pair_solref, rtol=1e-6)
    assert g1.mj.npair > 0  # the pairs are checked on a model that has them

    env = envs.make("go1", friction_min=0.3, friction_max=0.5, action_noise=0.05,
                    softness_min=1.0, softness_max=5.0)
    keys = jax.random.key_data(jax.random.split(jax.random.key(0), 8))
    states = jax.jit(jax.vmap(env.reset))(keys)
    f, k = np.asarray(states.info["friction"]), np.asarray(states.info["softness"])
    assert ((f >= 0.3) & (f <= 0.5)).all() and np.ptp(f) > 0.05
    assert ((k >= 1.0) & (k <= 5.0)).all() and np.ptp(k) > 0.5
    plain = envs.make("go1").reset(keys[0]).info
    assert (float(plain["friction"]), float(plain["softness"])) == (1.0, 1.0)

    s0 = jax.tree.map(lambda x: x[0], states)
    other = s0.replace(info={**s0.info, "rng": jax.random.key_data(jax.random.key(7))})
    step = jax.jit(env.step)
    a = jnp.zeros(env.action_size)
    q1, q2 = step(s0, a).pipeline_state.qpos, step(other, a).pipeline_state.qpos
    assert float(jnp.abs(q1 - q2).max()) > 1e-6  # the noise differs with the key
    np.testing.assert_array_equal(q1, step(s0, a).pipeline_state.qpos)  # and is the key's

    for bad in (dict(friction_min=0.0), dict(friction_min=0.6, friction_max=0.5),
                dict(softness_min=0.0), dict(softness_min=3.0, softness_max=2.0),
                dict(action_noise=-0.1), dict(tilt_max_deg=90.0), dict(tilt_s=0.0),
                dict(tilt_friction_margin=-0.5), dict(tilt_friction_margin=float("nan"))):
        with pytest.raises(ValueError, match="friction|softness|action_noise|tilt"):
            envs.config("go1", **bad)


def test_sensor_noise_reaches_the_observation_and_nothing_else(go1_env):
    """``sensor_noise``: from the same state, action and key the world, the reward and the
    termination are the exact environment's; the observation is :func:`envs.observe` of
    :func:`sensors.measure` of the true state with the period's key, and its base-velocity block
    is off by the sensors' scale (0.02 m/s x 3, rotated into the body frame)."""
    from stride_jax.sim import sensors

    plain, noisy = go1_env, envs.make("go1", sensor_noise=3.0)
    keys = jax.random.key_data(jax.random.split(jax.random.key(1), 64))
    s_plain, s_noisy = jax.vmap(plain.reset)(keys), jax.vmap(noisy.reset)(keys)
    np.testing.assert_array_equal(s_plain.pipeline_state.qpos, s_noisy.pipeline_state.qpos)
    a = 0.3 * jnp.ones((64, plain.action_size))

    def step(env, s):  # (XLA's backend optimisations: a third of the compile time, unneeded)
        fn = jax.jit(jax.vmap(env.step))
        return fn.lower(s, a).compile({"xla_backend_optimization_level": 0})(s, a)

    n_plain, n_noisy = step(plain, s_plain), step(noisy, s_noisy)
    # Two programs, which XLA may fuse apart: the same float32 world up to rounding, which the
    # contact solver amplifies (2e-6 m/s seen in CI); the sensors' smallest term, were it to
    # reach the world, is 10x the tolerance (encoder 6e-4 rad, joint rates 0.09 rad/s here).
    for name in ("qpos", "qvel"):
        np.testing.assert_allclose(getattr(n_plain.pipeline_state, name),
                                   getattr(n_noisy.pipeline_state, name), rtol=1e-4, atol=5e-5)
    np.testing.assert_allclose(n_plain.reward, n_noisy.reward, rtol=1e-4, atol=1e-6)
    np.testing.assert_array_equal(n_plain.done, n_noisy.done)

    # the observation, rebuilt by hand from the true state and the period's key
    q, qd = n_noisy.pipeline_state.qpos, n_noisy.pipeline_state.qvel
    noise = sensors.SensorNoise().scaled(3.0)

    def by_hand(q, qd, rng, command):
        _, k_cmd = jax.random.split(rng)
        qm, qdm = sensors.measure(noise, q, qd, jax.random.fold_in(k_cmd, 5), floating_base=True)
        return envs.observe(noisy.cfg, noisy.home, qm, qdm, command)

    want = jax.vmap(by_hand)(q, qd, s_noisy.info["rng"], n_noisy.info["command"])
    np.testing.assert_allclose(n_noisy.obs, want, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(n_plain.obs, jax.vmap(plain.observation_fn())(
        n_plain.pipeline_state.qpos, n_plain.pipeline_state.qvel, n_plain.info["command"]),
        rtol=1e-6, atol=1e-6)
    spread = float(jnp.std(n_noisy.obs[:, :3] - n_plain.obs[:, :3]))
    assert 0.04 < spread < 0.09, spread  # 0.06 m/s per axis
    with pytest.raises(ValueError, match="sensor_noise"):
        envs.config("go1", sensor_noise=-1.0)


def test_a_randomised_slope_builds_up_and_the_policy_senses_it(go1):
    """``tilt_max_deg``: each reset draws the episode's slope and uphill heading; gravity tilts
    linearly over ``tilt_s`` (level at the start, as the closed loop's ``tilt`` scenario) and the
    observation's gravity is the tilted one in the base frame; without it the streams and
    states are those of level ground."""
    env = envs.make("go1", tilt_max_deg=20.0, tilt_s=0.1)
    keys = jax.random.key_data(jax.random.split(jax.random.key(0), 8))
    states = jax.jit(jax.vmap(env.reset))(keys)
    tilt = np.asarray(states.info["tilt"])
    assert ((tilt[:, 0] >= 0) & (tilt[:, 0] <= np.deg2rad(20.0))).all() and np.ptp(tilt[:, 1]) > 1
    level = envs.make("go1")
    np.testing.assert_array_equal(level.reset(keys[0]).info["tilt"], [0, 0])
    np.testing.assert_array_equal(level.reset(keys[0]).obs, env.reset(keys[0]).obs)  # level at 0
    g = np.asarray(go1.mj.opt.gravity)
    np.testing.assert_allclose(scenarios.gravity_at(jnp.array([0.3, 0.1]), 0.05, g),
                               9.81 * np.array([-np.sin(0.15), 0, -np.cos(0.15)]), rtol=1e-5)
    s = jax.tree.map(lambda x: x[0], states)
    step = jax.jit(env.step)
    a = jnp.zeros(env.action_size)
    for _ in range(6):  # past tilt_s: the full slope
        s = step(s, a)
    slope, heading = s.info["tilt"]
    up = scenarios.gravity_at(jnp.array([slope, 0.1]), 1.0, g, heading) / 9.81
    q, qd = s.pipeline_state.qpos, s.pipeline_state.qvel
    np.testing.assert_allclose(s.obs[6:9], envs.base_signals(q, qd, up)[2], atol=1e-5)
    first = jax.tree.map(lambda x: x[0], states)  # the same episode on a slope of 0 (one compile)
    flat = first.replace(info={**first.info, "tilt": jnp.zeros(2)})
    for _ in range(6):
        flat = step(flat, a)
    assert float(jnp.abs(flat.pipeline_state.qpos - q).max()) > 1e-4  # the slope moved it


def test_a_slope_is_drawn_no_steeper_than_the_episodes_friction_holds(go1):
    """``tilt_friction_margin``: with friction and slope both randomised each episode's slope
    satisfies ``tan(slope) <= margin * mu * factor`` (``mu`` the feet's friction on the floor,
    0.8 for the Go1), the same key drawing the same fraction of the reachable range; apart
    (margin 0), slippery episodes get slopes no stance holds."""
    kw = dict(friction_min=0.3, friction_max=1.2, tilt_max_deg=25.0)
    apart, bound = envs.make("go1", **kw), envs.make("go1", tilt_friction_margin=0.9, **kw)
    assert bound.foot_mu == pytest.approx(0.8)  # the Menagerie Go1's feet (MuJoCo's max rule)
    keys = jax.random.key_data(jax.random.split(jax.random.key(0), 256))
    a, b = (jax.jit(jax.vmap(e.reset))(keys).info for e in (apart, bound))
    np.testing.assert_array_equal(a["friction"], b["friction"])
    holds = 0.9 * 0.8 * np.asarray(b["friction"])
    assert (np.tan(np.asarray(b["tilt"][:, 0])) <= holds * (1 + 1e-5)).all()
    assert (np.tan(np.asarray(a["tilt"][:, 0])) > 0.8 * np.asarray(a["friction"])).any()
    steepest = np.minimum(np.deg2rad(25.0), np.arctan(holds))
    np.testing.assert_allclose(np.asarray(b["tilt"][:, 0]) / steepest,
                               np.asarray(a["tilt"][:, 0]) / np.deg2rad(25.0), rtol=1e-5)


def test_a_slope_can_be_drawn_steep_and_facing_up_the_start(go1):
    """``tilt_min_deg`` / ``tilt_heading_deg``: each episode's slope in [min, max] degrees and its
    uphill direction within +-heading of the robot's drawn heading at the start, the same key
    drawing the same fractions of the ranges; the defaults (from level, any direction) are the
    draws of before, bit for bit; a bound out of range is a clear error."""
    keys = jax.random.key_data(jax.random.split(jax.random.key(1), 256))
    wide = jax.jit(jax.vmap(envs.make("go1", tilt_max_deg=20.0).reset))(keys).info["tilt"]
    s = jax.jit(jax.vmap(envs.make("go1", tilt_max_deg=20.0, tilt_min_deg=10.0,
                                   tilt_heading_deg=30.0).reset))(keys)
    quat = np.asarray(s.pipeline_state.qpos[:, 3:7])
    yaw = 2 * np.arctan2(quat[:, 3], quat[:, 0])  # the start's heading (a turn about z)
    assert np.ptp(yaw) > 3  # drawn: uphill relative to it is not uphill along +x
    slope = np.rad2deg(np.asarray(s.info["tilt"][:, 0]))
    off = np.rad2deg(np.angle(np.exp(1j * (np.asarray(s.info["tilt"][:, 1]) - yaw))))
    assert (slope >= 10 - 1e-4).all() and (slope <= 20 + 1e-4).all() and np.ptp(slope) > 8
    assert (np.abs(off) <= 30 + 1e-3).all() and np.ptp(off) > 50
    np.testing.assert_allclose((slope - 10) / 10, np.rad2deg(np.asarray(wide[:, 0])) / 20,
                               rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(off / 30, np.rad2deg(np.asarray(wide[:, 1])) / 180,
                               rtol=1e-4, atol=1e-4)
    # the draws of before these two fields: slope max * u, heading uniform in [-pi, pi]
    k = jax.random.key_data(jax.random.key(2))
    info = envs.make("go1", tilt_max_deg=20.0).reset(k).info
    k_clock = jax.random.split(k, 5)[4]  # reset's split: rng, joints, yaw, command, clock
    assert float(info["tilt"][1]) == float(jax.random.uniform(
        jax.random.fold_in(k_clock, 3), minval=-jnp.pi, maxval=jnp.pi))
    assert float(info["tilt"][0]) == float(
        jnp.deg2rad(20.0) * jax.random.uniform(jax.random.fold_in(k_clock, 2)))
    for bad in (dict(tilt_max_deg=10.0, tilt_min_deg=12.0), dict(tilt_min_deg=-1.0),
                dict(tilt_max_deg=10.0, tilt_heading_deg=190.0),
                dict(tilt_max_deg=10.0, tilt_heading_deg=-5.0), dict(tilt_heading_deg=30.0)):
        with pytest.raises(ValueError, match="tilt_min_deg|tilt_heading_deg"):
            envs.config("go1", **bad)



def test_a_randomised_payload_loads_the_named_body(go1):
    """``payload_max`` / ``payload_body``: each reset draws the episode's load in [0,
    payload_max] of the robot's mass; a step is the step of the robot with that load strapped on
    the named body by the closed loop's own edit (``randomize.add_payload`` on a MuJoCo copy),
    and not the step with it on the base; bad settings and unknown bodies are clear errors."""
    import copy

    from stride_jax.sim import model as sim_model, randomize

    env = envs.make("go1", payload_max=0.5, payload_body="FR_thigh")
    keys = jax.random.key_data(jax.random.split(jax.random.key(3), 16))
    s = jax.vmap(env.reset)(keys)
    kg = np.asarray(s.info["payload"])
    assert np.all((kg >= 0) & (kg <= 0.5 * env.robot_mass)) and np.ptp(kg) > 0.1 * env.robot_mass
    one = jax.tree.map(lambda x: x[0], s)
    action = 0.3 * jnp.ones(env.action_size)

    def step(e):  # (XLA's backend optimisations: a third of the compile time, unneeded)
        return jax.jit(e.step).lower(one, action).compile(
            {"xla_backend_optimization_level": 0})(one, action).pipeline_state

    def loaded_on(body):  # the same episode's load, on a MuJoCo copy
        m = copy.copy(go1.mj)
        randomize.add_payload(m, sim_model.body_id(go1, body), float(kg[0]))
        return envs.VelocityEnv(envs.config("go1"), mj_model=m)

    # the edit: the body's mass and rotational inertia scale together, every other body's stay
    body = sim_model.body_id(go1, "FR_thigh")
    mass, inertia = randomize.payload_fields(go1.mj.body_mass, go1.mj.body_inertia, body, 2.0, np)
    m0 = go1.mj.body_mass[body]
    np.testing.assert_allclose(mass - go1.mj.body_mass, 2.0 * (np.arange(len(mass)) == body))
    np.testing.assert_allclose(inertia[body], go1.mj.body_inertia[body] * (m0 + 2.0) / m0)
    np.testing.assert_array_equal(np.delete(inertia, body, 0), np.delete(go1.mj.body_inertia, body, 0))
    drawn, thigh, base = step(env), step(loaded_on("FR_thigh")), step(loaded_on(""))
    np.testing.assert_allclose(drawn.qvel, thigh.qvel, atol=1e-4)
    assert float(jnp.max(jnp.abs(drawn.qvel - base.qvel))) > 1e-2  # where it sits matters
    for bad, match in [(dict(payload_max=-0.1), "payload_max"),
                       (dict(payload_max=float("nan")), "payload_max"),
                       (dict(payload_body="trunk"), "names a body for no payload")]:
        with pytest.raises(ValueError, match=match):
            envs.config("go1", **bad)
    with pytest.raises(ValueError, match="'backpack' is not a body of 'go1'; its bodies: trunk"):
        envs.make("go1", payload_max=0.2, payload_body="backpack")
    massless = copy.copy(go1.mj)
    massless.body_mass[body] = 0.0
    with pytest.raises(ValueError, match="has no mass"):
        envs.VelocityEnv(envs.config("go1", payload_max=0.2, payload_body="FR_thigh"), massless)
    with pytest.raises(ValueError, match="FR_thigh: body .* has no mass"):
        randomize.add_payload(massless, body, 1.0)


def test_command_schedules_draw_each_world_its_own_commands_within_the_ranges():
    """``W`` schedules of ``P`` pieces ``change_s`` apart: every value inside the commands'
    bounds (or zero, the standing draws), the worlds' schedules different, one key one draw."""
    c = envs.config("go1").commands
    starts, values = envs.command_schedules(c, jax.random.key(3), 5, 4, 0.5)
    np.testing.assert_allclose(starts, [0.0, 0.5, 1.0, 1.5])
    assert values.shape == (5, 4, 3)
    lo, hi = (np.asarray(b) for b in c.bounds())
    v = np.asarray(values)
    assert ((v >= lo - 1e-6) & (v <= hi + 1e-6) | (v == 0)).all()
    assert not np.allclose(v[0], v[1])
    again = envs.command_schedules(c, jax.random.key(3), 5, 4, 0.5)[1]
    np.testing.assert_array_equal(v, np.asarray(again))
