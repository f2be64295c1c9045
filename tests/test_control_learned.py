"""Learned reward and value models fit known functions; lambda-returns match their definition."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from stride_jax.control import learned

CFG = learned.LearnedConfig(width=64, depth=2, steps=600, rounds=5, batch=256,
                            learning_rate=3e-3, discount=0.9, lam=0.95)


def _data(key, n=64, t=20):
    """Worlds that stand still (s' = s), reward sin(3 s0) + 0.5 + a term in the action."""
    k_s, k_a = jax.random.split(key)
    s = jax.random.uniform(k_s, (n, 1, 2), minval=-1, maxval=1) * jnp.ones((1, t, 1))
    a = jax.random.uniform(k_a, (n, t, 1), minval=-1, maxval=1)
    r = jnp.sin(3 * s[..., 0]) + 0.5 - (a[..., 0] - 0.3) ** 2
    zeros = jnp.zeros((n, t))
    return learned.Trajectories(s, a, r, s, zeros, zeros)


def test_reward_model_fits_a_known_function():
    train, test = _data(jax.random.key(0)), _data(jax.random.key(1), n=32)
    params, losses = jax.jit(lambda k, d: learned.fit_reward(k, CFG, d))(jax.random.key(2), train)
    pred = jax.vmap(jax.vmap(lambda o, a: learned.apply(params, learned.reward_input(o, a))))(
        test.obs, test.action)
    assert losses[-1] < 0.1 * losses[0]
    assert learned.r2(pred, test.reward) > 0.95


def test_value_model_fits_the_discounted_sum_of_a_constant_reward():
    # The action is uniform on [-1, 1], so E[-(a - 0.3)^2] = -(1/3 + 0.09); the states never move:
    # V(s) = (sin(3 s0) + 0.5 - 0.4233) / (1 - gamma).
    data = _data(jax.random.key(0), n=128)
    params, losses = jax.jit(lambda k, d: learned.fit_value(k, CFG, d))(jax.random.key(3), data)
    s0 = jnp.linspace(-1, 1, 41)
    obs = jnp.stack([s0, jnp.zeros_like(s0)], axis=-1)
    v = jax.vmap(lambda o: learned.apply(params, o))(obs)
    exact = (jnp.sin(3 * s0) + 0.5 - (1 / 3 + 0.09)) / (1 - CFG.discount)
    assert losses.shape == (CFG.rounds, CFG.steps)
    err = jnp.max(jnp.abs(v - exact)) / (jnp.max(exact) - jnp.min(exact))
    assert err < 0.1, float(err)


def test_input_noise_flattens_the_value_along_an_input_the_rollouts_barely_moved():
    """``fit_value(input_noise=...)``: on worlds whose second input spans only +-0.05 while the
    reward rises steeply with it, the plain value learns that slope; noise of 3 spreads on that
    input takes most of it away (regression on noisy inputs attenuates a slope by about
    spread^2 / (spread^2 + noise^2) = 0.1), while the value along the first input, noised not,
    still fits."""
    n, t = 128, 20
    k_s, k_b, k_a = jax.random.split(jax.random.key(0), 3)
    s0 = jax.random.uniform(k_s, (n, 1, 1), minval=-1, maxval=1)
    s1 = jax.random.uniform(k_b, (n, 1, 1), minval=-0.05, maxval=0.05)
    s = jnp.concatenate([s0, s1], -1) * jnp.ones((1, t, 1))
    a = jax.random.uniform(k_a, (n, t, 1), minval=-1, maxval=1)
    r = jnp.sin(3 * s[..., 0]) + 10 * s[..., 1]
    zeros = jnp.zeros((n, t))
    data = learned.Trajectories(s, a, r, s, zeros, zeros)

    def fit(noise):
        params, _ = jax.jit(lambda k, d: learned.fit_value(k, CFG, d, noise))(
            jax.random.key(3), data)
        return jax.vmap(lambda o: learned.apply(params, o))

    plain, noised = fit(None), fit(jnp.array([0.0, 3.0]))
    grid = jnp.linspace(-0.8, 0.8, 17)

    def slope(v):  # dV/ds1 across the rollouts' range of s1, averaged over s0
        hi = v(jnp.stack([grid, jnp.full_like(grid, 0.05)], -1))
        lo = v(jnp.stack([grid, jnp.full_like(grid, -0.05)], -1))
        return float(jnp.mean(hi - lo) / 0.1)

    exact = 10 / (1 - CFG.discount)
    assert slope(plain) > 0.5 * exact, (slope(plain), exact)
    assert abs(slope(noised)) < 0.3 * slope(plain), (slope(noised), slope(plain))
    on_s0 = noised(jnp.stack([grid, jnp.zeros_like(grid)], -1))
    want = jnp.sin(3 * grid) / (1 - CFG.discount)
    err = jnp.max(jnp.abs(on_s0 - want)) / (jnp.max(want) - jnp.min(want))
    assert err < 0.15, float(err)
    with pytest.raises(ValueError, match=r"input_noise must have shape \[2\]"):
        learned.fit_value(jax.random.key(3), CFG, data, jnp.zeros(3))
    with pytest.raises(ValueError, match="finite and >= 0"):
        learned.fit_value(jax.random.key(3), CFG, data, jnp.array([0.0, -1.0]))


def test_lambda_returns_match_their_definition():
    r = jnp.array([1.0, 2.0, 3.0, 4.0])
    v = jnp.array([10.0, 20.0, 30.0, 40.0])  # V of the next observation
    none = jnp.zeros(4)
    g, lam = 0.9, 1.0
    out = learned.lambda_returns(r, v, none, none, g, lam)
    expect = [sum(g ** k * r[t + k] for k in range(4 - t)) + g ** (4 - t) * v[-1]
              for t in range(4)]
    np.testing.assert_allclose(out, expect, rtol=1e-6)
    # A fall at step 1 cuts the return there; a time-limit reset at step 2 bootstraps from V.
    term = jnp.array([0.0, 1.0, 0.0, 0.0])
    reset = jnp.array([0.0, 1.0, 1.0, 0.0])
    out = learned.lambda_returns(r, v, term, reset, g, 0.5)
    np.testing.assert_allclose(out[1], r[1])
    np.testing.assert_allclose(out[2], r[2] + g * v[2])
    np.testing.assert_allclose(out[0], r[0] + g * (0.5 * v[0] + 0.5 * out[1]))


def test_bad_inputs_are_clear_errors():
    with pytest.raises(ValueError, match="discount"):
        learned.LearnedConfig(discount=1.0)
    d = _data(jax.random.key(0), n=4, t=3)
    with pytest.raises(ValueError, match="obs must be"):
        learned.fit_reward(jax.random.key(0), CFG, d._replace(obs=d.obs[:, :2]))
    params = learned.init(jax.random.key(0), CFG, jnp.zeros((5, 3)), jnp.zeros(5))
    with pytest.raises(ValueError, match="input must have shape"):
        learned.apply(params, jnp.zeros(4))


def test_fit_reward_value_flags_nest_the_learned_config_with_the_flat_flags_kept():
    import argparse

    from stride_jax import config
    from stride_jax.jobs import fit_reward_value as job

    parser = argparse.ArgumentParser()
    config.add_flags(parser, job.FitConfig)
    new = config.from_flags(job.FitConfig, parser.parse_args(
        ["--learned.steps", "5", "--learned.width", "8", "--envs", "4"]), job.FIT_PRESETS["tiny"])
    old = config.from_flags(job.FitConfig, parser.parse_args(
        ["--steps", "5", "--width", "8", "--envs", "4"]), job.FIT_PRESETS["tiny"])
    assert new == old and new.learned == dataclasses.replace(learned.PRESETS["tiny"], steps=5,
                                                             width=8)
    assert job.FitConfig().learned == learned.LearnedConfig()  # one source of the defaults


def test_a_reward_ensemble_is_stored_and_planned_against_with_its_members_mean(tmp_path):
    """Saved with its members, read back as one reward (the first member) by readers that want
    one and as the list with ``ensemble=True``; the planner's running cost is minus the members'
    mean reward, a single reward's is unchanged."""
    lc = learned.LearnedConfig(width=8, depth=1)
    r0 = learned.init(jax.random.key(0), lc, jnp.ones((4, 5)), jnp.ones(4))
    r1 = {**r0, "y_mean": r0["y_mean"] + 1.0}
    r2 = {**r0, "y_mean": r0["y_mean"] - 4.0}
    v = learned.init(jax.random.key(1), lc, jnp.ones((4, 3)), jnp.ones(4))
    path = tmp_path / "reward_value.msgpack"
    learned.save(path, [r0, r1, r2], [v, v])
    one, _ = learned.load(path)
    members, values = learned.load(path, ensemble=True)
    assert isinstance(one, dict) and len(members) == 3 and len(values) == 2
    np.testing.assert_array_equal(one["y_mean"], r0["y_mean"])
    np.testing.assert_array_equal(members[2]["y_mean"], r2["y_mean"])
    obs, u = jnp.array([0.3, -0.2, 0.5]), jnp.array([0.1, -0.4])
    rs = np.array([float(learned.apply(r, learned.reward_input(obs, u))) for r in (r0, r1, r2)])
    cost, _ = learned.planner_terms(members, values, lambda q, qd: q)
    np.testing.assert_allclose(float(cost(obs, None, u, 0)), -rs.mean(), rtol=1e-5)
    single, _ = learned.planner_terms(r0, v, lambda q, qd: q)
    np.testing.assert_allclose(float(single(obs, None, u, 0)), -rs[0], rtol=1e-6)


def test_relabelled_rewards_are_the_environments_under_the_new_command():
    """Steps relabelled to another command get the reward the environment's own functions
    (``envs.state_terms``, ``envs.total_reward``) give the same next state under it; stops and
    clipped steps stay as they were; share 0 changes nothing."""
    from stride_jax.control import envs
    cfg = envs.PRESETS["g1"]  # a task with a gait clock in its observation
    nu, n, t, dt = 4, 6, 3, 0.02
    home = jnp.zeros(nu)
    k = jax.random.split(jax.random.key(0), 4)
    quat = jnp.array([1.0, 0.0, 0.0, 0.0])
    q = jnp.concatenate([jnp.broadcast_to(jnp.array([0.0, 0.0, 0.75]), (n, t, 3)),
                         jnp.broadcast_to(quat, (n, t, 4)), jnp.zeros((n, t, nu))], -1)
    qd = jnp.concatenate([0.5 * jax.random.normal(k[0], (n, t, 6)), jnp.zeros((n, t, nu))], -1)
    cmd = jax.random.uniform(k[1], (n, t, 3), minval=jnp.array([0.3, -0.3, -0.5]),
                             maxval=jnp.array([1.0, 0.3, 0.5]))
    cmd = cmd.at[0].set(0.0)  # world 0 stands still
    clock = jnp.zeros((n, t))

    def reward(c):  # the environment's, at the next state (here the same state)
        def one(q_, qd_, c_):
            terms = envs.state_terms(cfg, home, q_, qd_, c_, jnp.zeros(nu), jnp.zeros((), bool))
            return envs.total_reward(cfg, terms, dt)[0]
        return jax.vmap(jax.vmap(one))(q, qd, c)

    obs = jax.vmap(jax.vmap(lambda q_, qd_, c_, k_: envs.observe(cfg, home, q_, qd_, c_, k_)))(
        q, qd, cmd, clock)
    r = reward(cmd).at[5, 0].set(0.0)  # one step as if the environment clipped it
    zeros = jnp.zeros((n, t))
    data = learned.Trajectories(obs, jnp.zeros((n, t, nu)), r, obs, zeros, zeros)
    new = learned.relabel_commands(data, cfg, dt, jax.random.key(3), share=1.0, std=0.5)
    c_new = new.obs[..., envs.obs_layout(cfg, nu)["command"]]
    moved = jnp.any(c_new != cmd, axis=-1)
    assert not moved[0].any() and moved[1:].all()  # the stop kept, the others moved
    np.testing.assert_array_equal(new.next_obs[..., envs.obs_layout(cfg, nu)["command"]], c_new)
    want = reward(c_new)
    np.testing.assert_allclose(np.asarray(new.reward)[1:5], np.asarray(want)[1:5], atol=1e-6)
    np.testing.assert_allclose(np.asarray(new.reward)[5, 1:], np.asarray(want)[5, 1:], atol=1e-6)
    assert float(new.reward[5, 0]) == 0.0 and float(new.reward[0, 0]) == float(r[0, 0])
    assert not np.allclose(np.asarray(new.reward)[1:], np.asarray(r)[1:])
    same = learned.relabel_commands(data, cfg, dt, jax.random.key(3), share=0.0, std=0.5)
    np.testing.assert_array_equal(same.reward, data.reward)
    np.testing.assert_array_equal(same.obs, data.obs)
    with pytest.raises(ValueError, match="not the velocity task's"):
        learned.relabel_commands(data._replace(obs=obs[..., 1:], next_obs=obs[..., 1:]), cfg,
                                 dt, jax.random.key(3), 1.0, 0.5)
    with pytest.raises(ValueError, match="observes through sensors"):
        learned.relabel_commands(data, dataclasses.replace(cfg, sensor_noise=1.0), dt,
                                 jax.random.key(3), 1.0, 0.5)
    with pytest.raises(ValueError, match="share=2"):
        learned.relabel_commands(data, cfg, dt, jax.random.key(3), 2.0, 0.5)


def test_the_fit_refuses_a_relabelling_it_cannot_do_before_any_rollout(monkeypatch):
    """``stride fit-reward-value --relabel-share``: the checks ``relabel_commands`` would make
    (``learned.check_relabel``) run before the policy is rolled out."""
    from stride_jax.jobs import fit_reward_value as job

    def never(*a, **k):
        raise AssertionError("rolled out before the check")

    monkeypatch.setattr(learned, "rollouts", never)
    with pytest.raises(ValueError, match="share=2"):
        job.fit_from_policy(job.FitConfig(policy="results/policies/ppo_go1", relabel_share=2.0))
    with pytest.raises(ValueError, match="std=-1"):
        job.fit_from_policy(job.FitConfig(policy="results/policies/ppo_go1", relabel_std=-1.0))


def test_the_fit_relabels_only_the_model_it_is_told(monkeypatch, tmp_path):
    """``stride fit-reward-value --relabel-models value`` (or ``reward``): the relabelled worlds
    train only that model; the other is the plain fit's, from the same rollouts and keys."""
    from stride_jax.control import envs
    from stride_jax.jobs import fit_reward_value as job

    def rollouts(env, policy, key, n, t):  # the velocity task's layout, moving commands
        o = envs.obs_size(env.cfg, env.action_size)
        k_o, k_c, k_r = jax.random.split(key, 3)
        obs = jax.random.normal(k_o, (n, t + 1, o))
        cmd = jax.random.uniform(k_c, (n, 1, 3), minval=0.3, maxval=0.8)
        obs = obs.at[..., envs.obs_layout(env.cfg, env.action_size)["command"]].set(
            jnp.broadcast_to(cmd, (n, t + 1, 3)))
        zeros = jnp.zeros((n, t))
        return learned.Trajectories(obs[:, :-1], jnp.zeros((n, t, env.action_size)),
                                    jax.random.uniform(k_r, (n, t), minval=0.5, maxval=1.0),
                                    obs[:, 1:], zeros, zeros)

    monkeypatch.setattr(learned, "rollouts", rollouts)
    fit = job.FIT_PRESETS["tiny"]

    def fitted(name, **kw):
        out = tmp_path / name
        job.fit_from_policy(dataclasses.replace(fit, policy="results/policies/ppo_go1",
                                                out=str(out), **kw), log=lambda *_: None)
        return learned.load(out / "reward_value.msgpack")

    def same(a, b):
        return all(jax.tree.leaves(jax.tree.map(lambda x, y: bool(jnp.array_equal(x, y)), a, b)))

    plain_r, plain_v = fitted("plain")
    for which in ("both", "value", "reward"):
        r, v = fitted(which, relabel_share=1.0, relabel_std=0.5, relabel_models=which)
        assert same(r, plain_r) == (which == "value"), which
        assert same(v, plain_v) == (which == "reward"), which
    with pytest.raises(ValueError, match="relabel_models must be one of"):
        fitted("bad", relabel_share=1.0, relabel_models="values")
    with pytest.raises(ValueError, match="no world is relabelled"):
        fitted("none", relabel_models="value")


def test_the_fit_noises_the_values_named_inputs_and_leaves_the_reward(monkeypatch, tmp_path):
    """``stride fit-reward-value --value-noise S --value-noise-parts P``: the value's noise
    vector is S on exactly the named parts of the task's layout; a fit with it (the default
    parts, the joints) leaves the reward the plain fit's bit for bit and changes the value;
    unknown parts and negative noise are refused before any rollout."""
    from stride_jax.control import envs
    from stride_jax.jobs import fit_reward_value as job

    cfg = envs.PRESETS["g1"]
    nu = 5
    o = envs.obs_size(cfg, nu)
    at = envs.obs_layout(cfg, nu)
    noise = np.asarray(job.value_input_noise(cfg, o, 0.5, "joint_pos"))
    assert noise.shape == (o,) and np.all(noise[at["joint_pos"]] == 0.5)
    assert np.count_nonzero(noise) == nu
    both = np.asarray(job.value_input_noise(cfg, o, 1.0, "joint_pos, joint_vel"))
    assert np.count_nonzero(both) == 2 * nu and np.all(both[at["joint_vel"]] == 1.0)
    assert job.value_input_noise(cfg, o, 0.0, "nonsense") is None  # off: nothing to read
    with pytest.raises(ValueError, match="unknown part"):
        job.value_input_noise(cfg, o, 0.5, "joint_position")
    with pytest.raises(ValueError, match="not the velocity task's"):
        job.value_input_noise(cfg, o + 1, 0.5, "joint_pos")

    def rollouts(env, policy, key, n, t):
        k_o, k_r = jax.random.split(key)
        obs = jax.random.normal(k_o, (n, t + 1, env.observation_size))
        zeros = jnp.zeros((n, t))
        return learned.Trajectories(obs[:, :-1], jnp.zeros((n, t, env.action_size)),
                                    jax.random.uniform(k_r, (n, t), minval=0.5, maxval=1.0),
                                    obs[:, 1:], zeros, zeros)

    monkeypatch.setattr(learned, "rollouts", rollouts)
    fit = dataclasses.replace(job.FIT_PRESETS["tiny"], policy="results/policies/ppo_go1")

    def fitted(name, **kw):
        out = tmp_path / name
        job.fit_from_policy(dataclasses.replace(fit, out=str(out), **kw), log=lambda *_: None)
        return learned.load(out / "reward_value.msgpack")

    def same(a, b):
        return all(jax.tree.leaves(jax.tree.map(lambda x, y: bool(jnp.array_equal(x, y)), a, b)))

    plain_r, plain_v = fitted("plain")
    r, v = fitted("noised", value_noise=0.5)
    assert same(r, plain_r) and not same(v, plain_v)

    def never(*a, **k):
        raise AssertionError("rolled out before the check")

    monkeypatch.setattr(learned, "rollouts", never)
    with pytest.raises(ValueError, match="unknown part"):
        fitted("bad", value_noise=0.5, value_noise_parts="posture")
    with pytest.raises(ValueError, match="finite and >= 0"):
        fitted("neg", value_noise=-0.5)
