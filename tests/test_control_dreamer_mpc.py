"""Dreamer-MPC (issue 19, item 2): policy-prior sampling, the discounted terminal value, rollouts
cut or down-weighted by the model's predicted error, the value's targets on the planner's own
rollouts, and a tiny closed loop in MJX with every switch on."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from mujoco import mjx

from stride_jax.control import envs, learned, mppi
from stride_jax.control import planner_value, planning as planning_lib
from stride_jax.jobs import closed_loop as cl, dreamer_mpc
from stride_jax.sim import rollout_mjx

DT, U_MAX = 0.05, 5.0


def pendulum(q, qd, u, key=None):
    qdd = u[0] - 9.81 * jnp.sin(q[0]) - 0.05 * qd[0]
    qd2 = qd + DT * qdd
    return q + DT * qd2, qd2


def pd_policy(q, qd):
    return -3.0 * q - 1.0 * qd


def zero_cost(q, qd, u, t):
    return jnp.zeros(())


def test_policy_prior_candidates_follow_the_policys_rollout():
    """Half the noise candidates are the policy acting through the model at its own small
    noise: they stay within a few noise std of the policy's rollout, while the plan-centred
    half (noise 2.0 around a plan at +3) does not."""
    q0, qd0 = jnp.array([0.5]), jnp.array([0.0])
    H, K = 6, 64
    cfg = mppi.MPPIConfig(samples=K, horizon=H, noise_std=2.0, prior_fraction=0.5,
                          prior_noise_std=0.05)
    planner = mppi.make(cfg, pendulum, zero_cost, [-U_MAX], [U_MAX], policy=pd_policy)
    state = planner.init(jax.random.key(0), jnp.full((H, 1), 3.0))
    _, _, info = jax.jit(planner.step)(state, q0, qd0)
    rollout, q, qd = [], q0, qd0
    for _ in range(H):
        rollout.append(pd_policy(q, qd))
        q, qd = pendulum(q, qd, rollout[-1])
    rollout = np.stack(rollout)  # [H, 1]
    dev = np.abs(np.asarray(info.candidates) - rollout[None]).mean(axis=(1, 2))  # [K]
    plan_group, prior_group = dev[:K // 2], dev[K // 2:]
    assert prior_group.max() < 0.15  # 3 x 0.05 (the closed loop damps the noise a little)
    assert plan_group.min() > 0.5
    # Off: every noise candidate is around the plan.
    off = mppi.make(dataclasses.replace(cfg, prior_fraction=0.0), pendulum, zero_cost,
                    [-U_MAX], [U_MAX], policy=pd_policy)
    _, _, info = jax.jit(off.step)(state, q0, qd0)
    assert np.abs(np.asarray(info.candidates) - rollout[None]).mean(axis=(1, 2)).min() > 0.5
    with pytest.raises(ValueError, match="needs a policy"):
        mppi.make(cfg, pendulum, zero_cost, [-U_MAX], [U_MAX])
    with pytest.raises(ValueError, match="two spellings"):
        mppi.MPPIConfig(prior_fraction=0.5, policy_noise=True)


def shift(q, qd, u, key=None):
    return q + u, qd


@pytest.mark.parametrize("gamma", [1.0, 0.9])
def test_the_terminal_value_is_added_at_the_horizon(gamma):
    """cost = sum_t gamma^t c_t - gamma^H V(x_H): with c = 1, V(q) = 10 q, no noise and a plan
    of 0.5 from q0 = 0.2 over H = 4 steps every candidate costs
    sum_(t<4) gamma^t - gamma^4 * 10 * (0.2 + 4 * 0.5)."""
    H = 4
    cfg = mppi.MPPIConfig(samples=8, horizon=H, noise_std=0.0, discount=gamma)
    planner = mppi.make(cfg, shift, lambda q, qd, u, t: jnp.ones(()), [-1.0], [1.0],
                        terminal_value=lambda q, qd: 10.0 * q[0])
    state = planner.init(jax.random.key(0), jnp.full((H, 1), 0.5))
    _, _, info = jax.jit(planner.step)(state, jnp.array([0.2]), jnp.zeros(1))
    expected = sum(gamma ** t for t in range(H)) - gamma ** H * 10.0 * (0.2 + H * 0.5)
    np.testing.assert_allclose(info.costs, expected, rtol=1e-5)
    np.testing.assert_array_equal(info.kept, H)


def risky(q, qd, u, key):
    """Pushing forward (u > 0) lands somewhere the model cannot tell (its draws spread by 50 in
    qd); holding back is certain."""
    return q + u, qd + jnp.where(u[0] > 0, 50.0 * jax.random.normal(key, (1,)), 0.0)


def _expected_cut_costs(actions, q0, bound, gamma, value, sigma):
    """Hand reference: per candidate, the step t at which sqrt(sum sigma^2) first exceeds the
    bound, the discounted unit running costs before it and -gamma^t V(x_t) at the cut."""
    costs, kept = [], []
    for a in np.asarray(actions)[..., 0]:
        q, err2, cost, t_cut = q0, 0.0, 0.0, len(a)
        for t, u in enumerate(a):
            err2 += sigma(u) ** 2
            if np.sqrt(err2) > bound:
                cost -= gamma ** t * value(q)
                t_cut = t
                break
            cost += gamma ** t
            q = q + u
        else:
            cost -= gamma ** len(a) * value(q)
        costs.append(cost)
        kept.append(t_cut)
    return np.array(costs), np.array(kept)


def test_a_rollout_with_large_predicted_error_is_cut_at_the_value():
    H, gamma, value = 3, 0.9, (lambda q: -q ** 2)
    unit = lambda q, qd, u, t: jnp.ones(())
    v = lambda q, qd: -q[0] ** 2
    # 1. The spread of 4 residual draws: a forward step is uncertain (spread ~50 >> 0.5).
    cfg = mppi.MPPIConfig(samples=64, horizon=H, noise_std=1.0, discount=gamma, error_draws=4,
                          error_bound=0.5)
    planner = mppi.make(cfg, risky, unit, [-1.0], [1.0], terminal_value=v)
    _, _, info = jax.jit(planner.step)(planner.init(jax.random.key(0)), jnp.array([0.3]),
                                       jnp.zeros(1))
    first = np.asarray(info.candidates)[:, 0, 0]
    assert (first > 0).any() and (first < 0).any()
    np.testing.assert_array_equal(np.asarray(info.kept)[first > 0], 0)  # cut at once
    np.testing.assert_allclose(np.asarray(info.costs)[first > 0], -value(0.3), rtol=1e-6)
    exp_costs, exp_kept = _expected_cut_costs(info.candidates, 0.3, 0.5, gamma, value,
                                              lambda u: 50.0 if u > 0 else 0.0)
    np.testing.assert_array_equal(info.kept, exp_kept)
    np.testing.assert_allclose(info.costs, exp_costs, rtol=1e-5, atol=1e-5)
    # 2. A learned one-step error estimate |u|: cut where sqrt(sum u^2) first exceeds 0.8.
    learned_cfg = dataclasses.replace(cfg, error_draws=1, error_bound=0.8)
    planner = mppi.make(learned_cfg, shift, unit, [-1.0], [1.0], terminal_value=v,
                        step_error=lambda q, qd, u: jnp.abs(u[0]))
    _, _, info = jax.jit(planner.step)(planner.init(jax.random.key(1)), jnp.array([0.3]),
                                       jnp.zeros(1))
    exp_costs, exp_kept = _expected_cut_costs(info.candidates, 0.3, 0.8, gamma, value, abs)
    assert 0 < (exp_kept < H).sum() < 64  # some cut, some not
    np.testing.assert_array_equal(info.kept, exp_kept)
    np.testing.assert_allclose(info.costs, exp_costs, rtol=1e-5, atol=1e-5)
    # 3. Down-weighting instead of cutting: the uncertain candidates lose weight.
    share = []
    for weight in (0.0, 0.1):
        c = mppi.MPPIConfig(samples=64, horizon=H, noise_std=1.0, error_draws=4,
                            error_weight=weight)
        planner = mppi.make(c, risky, lambda q, qd, u, t: (q[0] - 1.0) ** 2, [-1.0], [1.0])
        _, _, info = jax.jit(planner.step)(planner.init(jax.random.key(2)), jnp.zeros(1),
                                           jnp.zeros(1))
        share.append(float(info.weights[np.asarray(info.candidates)[:, :, 0].max(1) > 0].sum()))
    assert share[0] > 0.9 and share[1] < 0.5  # forward serves the task; the penalty wins
    with pytest.raises(ValueError, match="predicted error"):
        mppi.make(mppi.MPPIConfig(error_bound=1.0), shift, unit, [-1.0], [1.0])


def _learned_params(go1, value_const=None):
    env_cfg = envs.config("go1")
    obs_n = envs.obs_size(env_cfg, 12)
    lc = learned.LearnedConfig(width=8, depth=1)
    r = learned.init(jax.random.key(0), lc, jnp.ones((4, obs_n + 12)), jnp.ones(4))
    v = learned.init(jax.random.key(1), lc, jnp.ones((4, obs_n)), jnp.ones(4))
    if value_const is not None:  # a constant value: zero network, the mean left
        v = {**v, "net": jax.tree.map(jnp.zeros_like, v["net"]),
             "y_mean": jnp.asarray(value_const, jnp.float32)}
    return env_cfg, r, v


def test_value_targets_from_planner_rollouts_match_a_hand_recursion(go1):
    """A model that sinks the base 0.1 m per step: the recorded candidates' rewards are the
    planner's own (-running cost), a step into a fallen state is terminal, and the targets are
    the lambda-returns bootstrapped with the value (here a constant 2.0), a fall ending them."""
    env_cfg, r_params, v_params = _learned_params(go1, value_const=2.0)
    sink = lambda q, qd, ctrl, key: (q.at[2].add(-0.1), qd)
    cfg = cl.ClosedLoopConfig(mppi=mppi.MPPIConfig(samples=8, horizon=4))
    planning = planning_lib.make_planning(cfg.planning, env_cfg, go1, sink,
                                          learned_params=(r_params, v_params))
    planner = planning_lib.make_planner(planning, planning_lib.mppi_config(cfg.mppi, cfg.planning,
                                                                           planning))
    q0 = planning_lib.augment(jnp.asarray(go1.info.qpos0), jnp.array([1.0, 0, 0]))
    qd0 = jnp.zeros(go1.mj.nv)
    u, _, info = planner.step(planner.init(jax.random.key(0)), q0, qd0)
    record = planner_value.make_record(planning, go1, None, 4, with_error=False)
    q1, _ = planning.dynamics(q0, qd0, u, jax.random.key(5))
    closed, cand, up, _ = record(q0, qd0, u, info, q1, qd0, jnp.zeros((), bool),
                                 jax.random.key(3))
    obs, act, rew, nxt, term, _ = (np.asarray(x) for x in cand)  # [M=4, H=4, ...]
    z0 = float(go1.info.qpos0[2])
    fall_at = [t for t in range(4) if z0 - 0.1 * (t + 1) < go1.robot.min_base_height][0]
    assert fall_at < 3  # the toy falls inside the horizon
    for m in range(4):
        for t in range(4):
            u_t = jnp.asarray(act[m, t]) * env_cfg.action_scale  # unclipped: ctrl = home + u
            q_t = q0.at[2].add(-0.1 * t)
            np.testing.assert_allclose(rew[m, t], -planning.cost(q_t, qd0, u_t, t), rtol=1e-5,
                                       atol=1e-6)
        np.testing.assert_array_equal(term[m], [float(t >= fall_at) for t in range(4)])
    traj = learned.Trajectories(*(jnp.asarray(x) for x in (obs, act, rew, nxt, term)),
                                jnp.zeros_like(jnp.asarray(rew)))
    pcfg = planner_value.PlannerValueConfig(discount=0.9, lam=0.5)
    g = np.asarray(planner_value.targets(v_params, traj, pcfg))
    for m in range(4):
        nxt_g = 2.0  # bootstrap at the horizon
        for t in reversed(range(4)):
            cont = 1.0 - term[m, t]
            nxt_g = rew[m, t] + 0.9 * cont * (0.5 * 2.0 + 0.5 * nxt_g)
            np.testing.assert_allclose(g[m, t], nxt_g, rtol=1e-5)
        np.testing.assert_allclose(g[m, fall_at], rew[m, fall_at], rtol=1e-6)  # a fall ends it
    assert bool(up) and np.asarray(closed[0]).shape == obs.shape[2:]


@pytest.mark.slow  # each switch: the tests above and below
def test_a_tiny_closed_loop_with_every_switch_on(go1):
    """Two MJX worlds, a stochastic toy model, the policy prior, a short discounted horizon,
    residual draws and a learned error estimate cutting rollouts: the planner plans, the data
    for the value and the error model come out finite, and both fits run."""
    env_cfg, r_params, v_params = _learned_params(go1)
    err_params = learned.init(jax.random.key(4), learned.LearnedConfig(width=8, depth=1),
                              jnp.ones((4, envs.obs_size(env_cfg, 12) + 12)), jnp.ones(4))

    def jitter(q, qd, ctrl, key):  # stands still, with a residual that varies per draw
        return q, qd + 0.05 * jax.random.normal(key, qd.shape)

    m = mppi.MPPIConfig(samples=8, horizon=3, policy_samples=2, prior_fraction=0.5,
                        discount=0.97, error_draws=2, error_bound=0.15, error_weight=0.1)
    cfg = cl.ClosedLoopConfig(mppi=m)
    ppo_policy = lambda obs, key: 0.1 * jnp.tanh(obs[:12])
    planning = planning_lib.make_planning(cfg.planning, env_cfg, go1, jitter, ppo_policy,
                                          (r_params, v_params), error_params=err_params)
    planner = planning_lib.make_planner(planning, planning_lib.mppi_config(cfg.mppi, cfg.planning,
                                                                           planning))
    mx = mjx.put_model(go1.mj)
    pcfg = dataclasses.replace(planner_value.PRESETS["tiny"], seconds=0.06)
    data = jax.jit(lambda k: planner_value.collect(planning, planner, go1, mx,
                                                   cl.mjx_step_fn(go1, mx), env_cfg, pcfg, k)
                   ).lower(jax.random.key(0)).compile(
        {"xla_backend_optimization_level": 0})(jax.random.key(0))
    assert data.up.shape == (2, 3) and bool(np.asarray(data.up).all())
    for leaf in jax.tree.leaves(data):
        assert np.isfinite(np.asarray(leaf)).all()
    assert np.asarray(data.cand.reward).shape == (2, 3 * 2, 3)
    assert float(np.asarray(data.err_y).max()) > 0  # the toy model is wrong somewhere
    new_v, err, report = planner_value.fit(jax.random.key(1), pcfg, v_params, data)
    assert err is not None and np.isfinite(report["value_after"]["bias_candidates"])
    assert report["closed_steps"] == 3 and report["candidate_steps"] == 3 * 2 * 3
    # A value ensemble: the first member is the single fit, the others bootstrap refits whose
    # spread the report measures where the closed loop went and along the candidates.
    ens, _, rep3 = planner_value.fit(jax.random.key(1),
                                     dataclasses.replace(pcfg, ensemble=3), v_params, data)
    assert isinstance(ens, list) and len(ens) == 3 and rep3["ensemble"] == 3
    for a_, b_ in zip(jax.tree.leaves(ens[0]), jax.tree.leaves(new_v)):
        np.testing.assert_array_equal(a_, b_)
    assert any(not np.array_equal(a_, b_) for a_, b_ in
               zip(jax.tree.leaves(ens[1]), jax.tree.leaves(ens[0])))
    for k in ("spread_closed", "spread_candidates"):
        assert np.isfinite(rep3["value_after"][k]) and rep3["value_after"][k] > 0


def test_a_value_ensemble_is_stored_and_planned_against_pessimistically(go1, tmp_path):
    """Saved with its members, read back as one value (the first member) by readers that want
    one; the planner's terminal value is w (mean - beta std) of the members, a single value's
    is unchanged."""
    _, r_params, v0 = _learned_params(go1)
    v1 = {**v0, "y_mean": v0["y_mean"] + 1.0}
    v2 = {**v0, "y_mean": v0["y_mean"] - 0.5}
    path = tmp_path / "reward_value.msgpack"
    learned.save(path, r_params, [v0, v1, v2])
    _, one = learned.load(path)
    _, members = learned.load(path, ensemble=True)
    assert isinstance(one, dict) and len(members) == 3
    np.testing.assert_array_equal(one["y_mean"], v0["y_mean"])
    np.testing.assert_array_equal(members[1]["y_mean"], v1["y_mean"])
    obs = jnp.linspace(-1.0, 1.0, v0["x_mean"].shape[0])
    vals = np.array([float(learned.apply(v, obs)) for v in (v0, v1, v2)])
    _, value = learned.planner_terms(r_params, members, lambda q, qd: q, 2.0, 1.5)
    np.testing.assert_allclose(float(value(obs, None)), 2.0 * (vals.mean() - 1.5 * vals.std()),
                               rtol=1e-5)
    _, single = learned.planner_terms(r_params, v0, lambda q, qd: q, 2.0, 1.5)
    np.testing.assert_allclose(float(single(obs, None)), 2.0 * vals[0], rtol=1e-6)
    learned.save(path, r_params, v0)  # a file without an ensemble reads as one value either way
    assert isinstance(learned.load(path, ensemble=True)[1], dict)


def test_ablation_variants_switch_one_thing_at_a_time(tmp_path):
    cfg = dreamer_mpc.AblationConfig()
    rows = {v: dreamer_mpc.variant_config(cfg, v, "planner.msgpack", "err.msgpack", 0.4)
            for v in dreamer_mpc.VARIANTS}
    assert rows["policy"].models == "policy"
    today = rows["mppi"].mppi
    assert today.prior_fraction == 0 and today.horizon == 20 and today.discount == 1.0
    assert rows["prior"].mppi == dataclasses.replace(today, prior_fraction=cfg.prior_fraction)
    assert rows["short"].mppi.horizon == cfg.short_horizon and rows["short"].mppi.discount < 1
    assert rows["short"].learned == cfg.learned and rows["value"].learned == "planner.msgpack"
    assert rows["value"].mppi.error_bound == 0 and rows["value"].error_model == ""
    assert rows["error"].mppi.error_bound == 0.4 and rows["error"].error_model == "err.msgpack"
    # prior_value: the full-horizon prior planner, the refitted value, discounted; nothing else
    pv = rows["prior_value"]
    assert pv.mppi == dataclasses.replace(rows["prior"].mppi, discount=cfg.discount)
    assert pv.learned == "planner.msgpack" and pv.error_model == ""
    assert pv.out.endswith("prior_value")
    with pytest.raises(ValueError, match="value_collector"):
        dreamer_mpc.AblationConfig(value_collector="value")
    # a value trained by an earlier call is reused only as it was asked for
    trained = dict(config=dataclasses.asdict(planner_value.PlannerValueConfig(worlds=32)))
    trained["config"].pop("ensemble")  # a report that predates a setting: its default
    want = planner_value.PlannerValueConfig(worlds=32)
    dreamer_mpc._check_reused_value(trained, want, tmp_path)
    with pytest.raises(ValueError, match=r"ensemble 1 \(asked 5\)"):
        dreamer_mpc._check_reused_value(trained, dataclasses.replace(want, ensemble=5), tmp_path)
    with pytest.raises(ValueError, match="unknown variants"):
        dreamer_mpc.AblationConfig(variants="mppi,magic")
    with pytest.raises(ValueError, match="NAME=RUN"):
        dreamer_mpc.AblationConfig(model="stride")


def test_the_planners_value_job_plans_with_a_reward_ensemble_and_keeps_it(go1, tmp_path,
                                                                           monkeypatch):
    """``dreamer_mpc.train_value`` over a file with ensembles (``stride fit-reward-value
    --members``): the planner that collects the data gets every member (as the closed loop
    plans), the value is refitted from the first member, and the written file keeps the reward
    ensemble whole (it read member 0 alone, and dropped the others, before). The simulator's
    collection and the fit are stand-ins here: the plumbing is what is tested (each is tested
    above)."""
    env_cfg, r0, v0 = _learned_params(go1)
    r1 = {**r0, "y_mean": r0["y_mean"] + 1.0}
    r2 = {**r0, "y_mean": r0["y_mean"] - 1.0}
    v1 = {**v0, "y_mean": v0["y_mean"] + 0.5}
    src = tmp_path / "in.msgpack"
    learned.save(src, [r0, r1, r2], [v0, v1])
    seen = {}

    def make_planning(cfg, env_cfg_, sm, step_fn, policy, learned_params, **kw):
        seen["learned"] = learned_params
        return "planning"

    def fit(key, cfg, value_params, data):
        seen["start"] = value_params
        return v1, None, dict(value_before={"r2_candidates": 0.0, "r2_closed": 0.0,
                                            "bias_candidates": 0.0},
                              value_after={"r2_candidates": 0.0, "r2_closed": 0.0,
                                           "bias_candidates": 0.0})

    monkeypatch.setattr(dreamer_mpc.sim_model, "load", lambda robot: go1)
    monkeypatch.setattr(dreamer_mpc.ppo, "load_policy", lambda path: (None, None, env_cfg))
    monkeypatch.setattr(dreamer_mpc.planning_lib, "make_planning", make_planning)
    monkeypatch.setattr(dreamer_mpc.planning_lib, "make_planner", lambda planning, m: "planner")
    monkeypatch.setattr(dreamer_mpc.planning_lib, "mppi_config", lambda m, p, planning: m)
    monkeypatch.setattr(dreamer_mpc.planner_value, "collect", lambda *a: type(
        "D", (), {"up": jnp.ones((2, 3), bool),
                  "closed": type("C", (), {"reward": jnp.zeros((2, 3))})()})())
    monkeypatch.setattr(dreamer_mpc.planner_value, "fit", fit)
    monkeypatch.setattr(dreamer_mpc.jax, "jit", lambda f: f)
    cl_cfg = cl.ClosedLoopConfig(policy="stand-in", learned=str(src))
    report = dreamer_mpc.train_value(cl_cfg, planner_value.PlannerValueConfig(), "oracle", "",
                                     tmp_path / "out", log=lambda *a: None, code="test")
    rewards, values = seen["learned"]
    assert isinstance(rewards, list) and len(rewards) == 3
    assert isinstance(values, list) and len(values) == 2
    assert float(seen["start"]["y_mean"]) == float(v0["y_mean"])  # refitted from member 0
    assert report["reward_members"] == 3 and report["value_members_planned"] == 2
    out_r, out_v = learned.load(tmp_path / "out" / "reward_value.msgpack", ensemble=True)
    assert [float(r["y_mean"]) for r in out_r] == [float(r["y_mean"]) for r in (r0, r1, r2)]
    assert float(out_v["y_mean"]) == float(v1["y_mean"])  # the refit's one value
