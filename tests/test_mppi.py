"""MPPI: solves a pendulum swing-up with the true dynamics, compiles once, is deterministic, and
refuses bad configurations."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from stride_jax.control import mppi
from stride_jax.dynamics import models

DT, U_MAX = 0.05, 5.0  # torque limit below m g l = 9.81: the swing-up must pump energy


def pendulum(q, qd, u, key=None):
    """Unit pendulum (q = 0 hanging), light damping, semi-implicit Euler."""
    qdd = u[0] - 9.81 * jnp.sin(q[0]) - 0.05 * qd[0]
    qd2 = qd + DT * qdd
    return q + DT * qd2, qd2


def cost(q, qd, u, t):
    err = jnp.mod(q[0] - jnp.pi + jnp.pi, 2 * jnp.pi) - jnp.pi  # angle from upright
    return err ** 2 + 0.05 * qd[0] ** 2 + 1e-3 * u[0] ** 2


CFG = mppi.MPPIConfig(samples=256, horizon=30, noise_std=2.0, temperature=0.05, smoothing=0.5)


def _closed_loop(planner, n_steps=160, seed=0):
    def body(carry, _):
        q, qd, state = carry
        u, state, info = planner.step(state, q, qd)
        q, qd = pendulum(q, qd, u)
        return (q, qd, state), (q[0], u[0])

    init = (jnp.zeros(1), jnp.zeros(1), planner.init(jax.random.key(seed)))
    _, (qs, us) = jax.jit(lambda c: jax.lax.scan(body, c, None, length=n_steps))(init)
    return np.asarray(qs), np.asarray(us)


def test_mppi_swings_the_pendulum_up_with_the_true_dynamics():
    planner = mppi.make(CFG, pendulum, cost, [-U_MAX], [U_MAX])
    qs, us = _closed_loop(planner)
    err = np.abs(np.mod(qs - np.pi + np.pi, 2 * np.pi) - np.pi)
    assert np.abs(us).max() <= U_MAX + 1e-6
    assert err[-40:].max() < 0.3  # upright over the last 2 s
    # Zero torque leaves it hanging: the task needs the planner.
    lazy = mppi.make(CFG, pendulum, cost, [-1e-3], [1e-3])
    lazy_q, _ = _closed_loop(lazy, 60)
    assert np.abs(lazy_q).max() < 0.01


def test_step_compiles_once_per_shape_and_is_deterministic():
    planner = mppi.make(mppi.MPPIConfig(samples=32, horizon=8), pendulum, cost, [-U_MAX], [U_MAX])
    step = jax.jit(planner.step)
    state = planner.init(jax.random.key(3))
    u1, s1, _ = step(state, jnp.array([0.1]), jnp.array([0.0]))
    u2, _, _ = step(s1, jnp.array([0.4]), jnp.array([1.0]))
    assert step._cache_size() == 1
    u1_again, _, _ = step(planner.init(jax.random.key(3)), jnp.array([0.1]), jnp.array([0.0]))
    np.testing.assert_array_equal(u1, u1_again)
    assert not np.array_equal(u1, u2)


def test_policy_candidates_and_terminal_value_are_used():
    # A policy that knows the answer (hold zero torque at the bottom) wins every sample's weight
    # when noise is huge and the cost penalises torque alone.
    planner = mppi.make(mppi.MPPIConfig(samples=64, horizon=5, noise_std=5.0, policy_samples=8),
                        pendulum, lambda q, qd, u, t: u[0] ** 2, [-U_MAX], [U_MAX],
                        terminal_value=lambda q, qd: 100.0 - q[0] ** 2,
                        policy=lambda q, qd: jnp.zeros(1))
    u, _, info = planner.step(planner.init(jax.random.key(0)), jnp.zeros(1), jnp.zeros(1))
    assert float(info.weights[-8:].sum()) > 0.5  # 8 of 64 candidates carry most of the weight
    assert abs(float(u[0])) < 0.5
    np.testing.assert_allclose(info.costs[-8:], -100.0, atol=1e-4)  # zero torque, value 100


@pytest.mark.parametrize("bad, match", [
    (dict(samples=0), "samples"), (dict(temperature=0.0), "temperature"),
    (dict(smoothing=1.0), "smoothing"), (dict(policy_samples=500), "policy_samples"),
    (dict(noise_std=-1.0), "noise_std"), (dict(unroll=0), "unroll")])
def test_bad_configs_are_clear_errors(bad, match):
    with pytest.raises(ValueError, match=match):
        mppi.MPPIConfig(**bad)


def test_unrolled_rollouts_plan_the_same():
    """Unrolling the horizon (for GPUs) changes how the step is compiled, not what it computes."""
    import dataclasses

    plans = []
    for unroll in (1, True):
        planner = mppi.make(dataclasses.replace(CFG, unroll=unroll), pendulum, cost, [-2.0], [2.0])
        state = planner.init(jax.random.key(0))
        u, state, _ = jax.jit(planner.step)(state, jnp.array([0.1]), jnp.array([0.0]))
        plans.append(np.asarray(state.plan))
    np.testing.assert_allclose(plans[0], plans[1], rtol=1e-4, atol=1e-5)  # float32 reordering


def test_bad_bounds_and_missing_policy_are_clear_errors():
    with pytest.raises(ValueError, match="upper bound"):
        mppi.make(CFG, pendulum, cost, [1.0], [-1.0])
    with pytest.raises(ValueError, match="needs a policy"):
        mppi.make(mppi.MPPIConfig(policy_samples=4), pendulum, cost, [-1.0], [1.0])


def test_bench_counts_every_model_evaluation(tmp_path):
    """The FLOP floor counts each substep and residual evaluation (XLA alone counts a loop body
    once): doubling the substeps or adding residual evaluations adds FLOPs."""
    import dataclasses

    from stride_jax.jobs import bench_mppi as bench
    from stride_jax.train.setup import model_config

    _, meta, spec, act = bench._robot("pendulum")
    cfg = model_config("stride", meta, 16, 1, 2)
    params = models.make("stride", spec, act, cfg).init(jax.random.key(0))
    base = bench.control_step_flops("stride", spec, act, cfg, params)
    twice = bench.control_step_flops("stride", spec, dataclasses.replace(
        act, n_substeps=2 * act.n_substeps), cfg, params)
    more = bench.control_step_flops("stride", spec, act, dataclasses.replace(cfg, nfe=4), params)
    assert base > 0 and twice == pytest.approx(2 * base) and more > base


def test_sharding_needs_sample_groups_that_split_over_its_devices():
    mesh = jax.sharding.Mesh(np.array(jax.local_devices()[:1] * 2), ("samples",))
    sharding = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("samples"))
    cfg = mppi.MPPIConfig(samples=9, horizon=4)
    with pytest.raises(ValueError, match="split evenly"):
        mppi.make(cfg, lambda q, qd, u, k: (q, qd), lambda q, qd, u, t: 0.0, -jnp.ones(1),
                  jnp.ones(1), sharding=sharding)


def test_policy_noise_perturbs_the_policy_in_closed_loop():
    """Without noise every candidate is the policy's own rollout, so the plan is exactly the
    actions the policy takes inside the model; with noise the candidates spread around it."""
    import dataclasses

    policy = lambda q, qd: -3.0 * q - 1.0 * qd  # a PD law, evaluated at each predicted state
    q0, qd0 = jnp.array([0.5]), jnp.array([0.0])
    cfg = mppi.MPPIConfig(samples=16, horizon=6, noise_std=0.0, policy_noise=True)
    planner = mppi.make(cfg, pendulum, cost, [-U_MAX], [U_MAX], policy=policy)
    u, state, info = jax.jit(planner.step)(planner.init(jax.random.key(0)), q0, qd0)
    expected, q, qd = [], q0, qd0
    for _ in range(6):
        expected.append(policy(q, qd))
        q, qd = pendulum(q, qd, expected[-1])
    np.testing.assert_allclose(state.plan, jnp.stack(expected), rtol=1e-5, atol=1e-6)
    assert float(jnp.ptp(info.costs)) < 1e-4  # identical candidates
    noisy = mppi.make(dataclasses.replace(cfg, noise_std=1.0), pendulum, cost, [-U_MAX], [U_MAX],
                      policy=policy)
    _, _, info = jax.jit(noisy.step)(noisy.init(jax.random.key(0)), q0, qd0)
    assert float(jnp.ptp(info.costs)) > 1e-3
    with pytest.raises(ValueError, match="policy_noise needs a policy"):
        mppi.make(cfg, pendulum, cost, [-U_MAX], [U_MAX])


def test_a_glitch_or_a_step_with_no_finite_rollout_falls_back_safely():
    """A non-finite state (a sensor glitch) or a step in which every rollout diverges applies the
    shifted previous plan, says so, stores nothing non-finite, and the next valid state plans."""
    cfg = mppi.MPPIConfig(samples=32, horizon=8, noise_std=1.0)
    planner = mppi.make(cfg, pendulum, cost, [-U_MAX], [U_MAX])
    step = jax.jit(planner.step)
    state = planner.init(jax.random.key(0))
    q, qd = jnp.array([0.5]), jnp.array([0.0])
    u, state, info = step(state, q, qd)
    assert int(info.status) == mppi.PLANNED and np.isfinite(np.asarray(u)).all()
    before = np.asarray(state.plan)
    u, state, info = step(state, jnp.array([np.nan]), qd)
    assert int(info.status) == mppi.BAD_STATE
    np.testing.assert_array_equal(np.asarray(u), before[1])  # the shifted previous plan
    assert np.isfinite(np.asarray(state.plan)).all()
    u, state, info = step(state, q, qd)
    assert int(info.status) == mppi.PLANNED and np.isfinite(np.asarray(state.plan)).all()

    def exploding(q, qd, u, key=None):
        return q * jnp.inf, qd * jnp.inf

    bad = mppi.make(cfg, exploding, cost, [-U_MAX], [U_MAX])
    s0 = bad.init(jax.random.key(1), jnp.full((8, 1), 0.7))
    u, s1, info = jax.jit(bad.step)(s0, q, qd)
    assert int(info.status) == mppi.NO_FINITE_ROLLOUT
    assert float(u[0]) == pytest.approx(0.7) and np.isfinite(np.asarray(s1.plan)).all()
    # with a policy, the policy acts where no rollout stayed finite (not on a glitch: its
    # action at a non-finite state means nothing, the shifted plan applies as above)
    guarded = mppi.make(dataclasses.replace(cfg, policy_samples=4), exploding, cost, [-U_MAX],
                        [U_MAX], policy=lambda q, qd: jnp.full(1, -0.3))
    u, s1, info = jax.jit(guarded.step)(s0, q, qd)
    assert int(info.status) == mppi.NO_FINITE_ROLLOUT and float(u[0]) == pytest.approx(-0.3)
    np.testing.assert_allclose(np.asarray(s1.plan)[:-1], 0.7)  # the shifted plan kept
    u, _, info = jax.jit(guarded.step)(s0, jnp.array([np.nan]), qd)
    assert int(info.status) == mppi.BAD_STATE and float(u[0]) == pytest.approx(0.7)


def _gamble(q, qd, u, key):
    """A one-step bet: pushing forward (u > 0) lands at 0 (70%) or 10 (30%), mean 3; holding
    back (u < 0) lands at 3.5 for sure. The landing point is the cost."""
    jump = jnp.where(jax.random.bernoulli(key, 0.3), 10.0, 0.0)
    return jnp.where(u > 0, jump, 3.5), qd


def _gamble_plan(**risk):
    cfg = mppi.MPPIConfig(samples=256, horizon=1, noise_std=1.0, temperature=0.05, **risk)
    planner = mppi.make(cfg, _gamble, lambda q, qd, u, t: jnp.zeros(()), [-1.0], [1.0],
                        terminal_value=lambda q, qd: -q[0])
    u, _, info = jax.jit(planner.step)(planner.init(jax.random.key(3)), jnp.zeros(1),
                                       jnp.zeros(1))
    return float(u[0]), info


def test_risk_aware_cost_prefers_the_safe_action_that_the_mean_rejects():
    """On a known bimodal model the mean over draws takes the bet (mean cost 3 < 3.5) and the
    CVaR of the worst 30% (cost 10 > 3.5) or a variance penalty declines it."""
    assert _gamble_plan(risk_draws=64, risk="mean")[0] > 0.3
    assert _gamble_plan(risk_draws=64, risk="cvar", risk_alpha=0.7)[0] < -0.3
    assert _gamble_plan(risk_draws=64, risk="std", risk_weight=1.0)[0] < -0.3
    # one draw per candidate: the 70% of risky candidates that drew the good outcome win
    assert _gamble_plan()[0] > 0.3


def _drift(q, qd, u, key):
    """Exposure ``u`` in [0, 1] to a wind of +-1 drawn from the key: ``x' = x + u w``."""
    return q + u * jnp.where(jax.random.bernoulli(key, 0.5), 1.0, -1.0), qd


def _drift_plan(latents):
    """Eight steps; exposure earns ``u`` a step, ending at ``x`` costs ``x^2 / 2``."""
    cfg = mppi.MPPIConfig(samples=256, horizon=8, noise_std=1.0, smoothing=0.9, temperature=0.05,
                          risk_draws=32, latents=latents)
    planner = mppi.make(cfg, _drift, lambda q, qd, u, t: -u[0], [0.0], [1.0],
                        terminal_value=lambda q, qd: -0.5 * q[0] ** 2)
    u, _, _ = jax.jit(planner.step)(planner.init(jax.random.key(4)), jnp.zeros(1), jnp.zeros(1))
    return float(u[0])


def test_latents_held_for_the_rollout_make_each_draw_one_world():
    """At a steady exposure ``u``: fresh draws every step average the wind out (E x^2 = 8 u^2:
    the best exposure is full, u = 1); held for the rollout each draw is one steady wind
    (E x^2 = 64 u^2: the best is u = 1/8)."""
    assert _drift_plan("step") > 0.7
    assert _drift_plan("rollout") < 0.35
    with pytest.raises(ValueError, match="latents"):
        mppi.MPPIConfig(latents="world")


def _noisy(q, qd, u, key):
    """``x' = x + u`` plus a draw of unit noise (also the velocity's), none for ``key=None``
    (the central sample)."""
    if key is None:
        return q + u, qd
    w = jax.random.normal(key, q.shape)
    return q + u + w, qd + w


def test_central_latents_rank_candidates_without_sampling_noise():
    """With ``latents="central"`` every candidate is scored by the model's central outcome:
    the costs are the noise-free ones whatever the planner's key (one draw each under
    ``"step"``), the observer-facing ``Planner.latents`` says so, and risk draws, which would
    all be equal, are refused. Error draws still draw beside the central rollout."""
    cost = lambda q, qd, u, t: (q[0] - 1.0) ** 2
    plan = lambda latents, key, **kw: jax.jit(mppi.make(
        mppi.MPPIConfig(samples=64, horizon=3, noise_std=0.5, latents=latents, **kw), _noisy,
        cost, [-1.0], [1.0]).step)(mppi.MPPIState(jnp.zeros((3, 1)), jax.random.key(key)),
                                   jnp.zeros(1), jnp.zeros(1))[2]
    a, b = plan("central", 0), plan("central", 1)
    # the candidates differ between keys, but each one's cost is its noise-free cost
    def clean(info):  # the running cost at x_0 = 0, x_1, x_2 (the state before each action)
        x = jnp.cumsum(info.candidates[..., 0], axis=1)
        return jnp.sum((jnp.concatenate([jnp.zeros((64, 1)), x[:, :-1]], 1) - 1.0) ** 2, 1)

    assert not np.array_equal(np.asarray(a.candidates), np.asarray(b.candidates))
    for info in (a, b):
        np.testing.assert_allclose(np.asarray(info.costs), np.asarray(clean(info)), rtol=1e-5)
    drawn = plan("step", 0)
    assert float(jnp.abs(drawn.costs - clean(drawn)).max()) > 0.1  # one draw each: noisy
    with_errors = plan("central", 0, error_draws=4, error_weight=1.0)
    assert float(with_errors.error.min()) > 0.1  # the draws' spread is still measured
    assert mppi.make(mppi.MPPIConfig(latents="central"), _noisy, cost, [-1.0], [1.0]).latents \
        == "central"
    with pytest.raises(ValueError, match="central.*deterministic"):
        mppi.MPPIConfig(latents="central", risk_draws=4)


def test_risk_cost_statistics():
    c = jnp.array([1.0, 2.0, 3.0, 10.0])
    assert float(mppi.risk_cost(c)) == pytest.approx(4.0)
    assert float(mppi.risk_cost(c, "cvar", 0.75)) == pytest.approx(10.0)
    assert float(mppi.risk_cost(c, "cvar", 0.5)) == pytest.approx(6.5)
    assert float(mppi.risk_cost(c, "std", weight=2.0)) == pytest.approx(4.0 + 2 * float(
        jnp.std(c)))
    assert not np.isfinite(float(mppi.risk_cost(jnp.array([1.0, jnp.inf]), "cvar", 0.5)))
    with pytest.raises(ValueError, match="risk="):
        mppi.MPPIConfig(risk="worst")
    with pytest.raises(ValueError, match="risk_draws"):
        mppi.MPPIConfig(risk_draws=0)


def test_bench_oracle_row_plans_through_mjx(tmp_path):
    """`stride bench-mppi` times planning through the robot's MJX model beside a learned model,
    and the table says how many times faster the learned model plans."""
    import dataclasses

    from stride_jax.jobs import bench_mppi as bench

    cfg = dataclasses.replace(bench.PRESETS["tiny"], out=str(tmp_path))
    rows = bench.run(cfg, "test")
    by = {r["model"]: r for r in rows}
    assert set(by) == {"delan", "oracle"}
    assert by["oracle"]["ms"] > 0 and by["oracle"]["kernel"] == "mjx"
    table = (tmp_path / "bench_mppi_cpu.md").read_text()
    oracle_line = [ln for ln in table.splitlines() if "| oracle |" in ln][0]
    delan_line = [ln for ln in table.splitlines() if "| delan |" in ln][0]
    assert delan_line.rstrip(" |").split("|")[-1].strip() == \
        f"{by['oracle']['ms'] / by['delan']['ms']:.1f}"
    assert oracle_line.rstrip().endswith("| - |")


def test_model_check_finds_a_model_that_misranks_candidates():
    """Candidates replayed through the truth: a perfect model has no error, ranks them as the
    truth does and has no regret; a model with the sign of its input flipped misranks them."""
    from stride_jax.control import model_check

    truth = lambda q, qd, u, k: (q + 0.1 * qd, qd + 0.1 * u)
    wrong = lambda q, qd, u, k: (q + 0.1 * qd, qd - 0.1 * u)
    cost = lambda q, qd, u, t: jnp.sum((q - 1.0) ** 2) + 0.01 * jnp.sum(u ** 2)
    zero = lambda q, qd: jnp.zeros(())
    cands = jax.random.normal(jax.random.key(0), (64, 8, 1))
    q, qd = jnp.zeros(8), jnp.zeros(8)  # 7 + one joint
    same = model_check.one_state(truth, truth, cost, zero, cands, q, qd, jax.random.key(1), 0.1, 1)
    assert float(same["spearman"]) == pytest.approx(1.0)
    assert float(same["regret"]) == pytest.approx(0.0, abs=1e-6)
    assert float(np.max(same["vel_err"])) == 0.0
    bad = model_check.one_state(wrong, truth, cost, zero, cands, q, qd, jax.random.key(1), 0.1, 1)
    assert float(bad["spearman"]) < 0.5 and float(bad["regret"]) > 0.0
    s = model_check.summarise(jax.tree.map(lambda x: jnp.stack([x, x]), bad), n_policy=8)
    assert s["states"] == 2 and len(s["vel_err_noise"]) == 8 and "vel_err_policy" in s


def test_model_check_signs_the_forward_speed_a_slow_model_misses():
    """A model that predicts half the truth's acceleration under-predicts the forward speed its
    plan reaches (negative forward bias along the plan), read in the base's heading: the same
    world motion seen from a base turned round reads the other way."""
    from stride_jax.control import model_check

    truth = lambda q, qd, u, k: (q + 0.1 * qd, qd + 0.1 * u)
    slow = lambda q, qd, u, k: (q + 0.1 * qd, qd + 0.05 * u)
    cost = lambda q, qd, u, t: (q[0] - 1.0) ** 2 + 0.01 * jnp.sum(u ** 2)
    zero = lambda q, qd: jnp.zeros(())
    cands = 1.0 + jax.random.normal(jax.random.key(0), (64, 8, 1))
    q, qd = jnp.zeros(8).at[3].set(1.0), jnp.zeros(8)  # identity quaternion: heading +x
    same = model_check.one_state(truth, truth, cost, zero, cands, q, qd, jax.random.key(1), 0.1, 1)
    assert float(jnp.max(jnp.abs(same["fwd_bias"]))) == 0.0
    bad = model_check.one_state(slow, truth, cost, zero, cands, q, qd, jax.random.key(1), 0.1, 1)
    plan_bias = np.asarray(bad["plan_fwd_model"] - bad["plan_fwd_true"])
    assert (plan_bias[1:] < 0).all() and (np.asarray(bad["plan_fwd_true"])[1:] > 0).all()
    turned = q.at[3:7].set(jnp.array([0.0, 0.0, 0.0, 1.0]))  # yaw pi: heading -x
    back = model_check.one_state(slow, truth, cost, zero, cands, turned, qd, jax.random.key(1), 0.1, 1)
    np.testing.assert_allclose(back["fwd_bias"], -np.asarray(bad["fwd_bias"]), atol=1e-6)
    s = model_check.summarise(jax.tree.map(lambda x: jnp.stack([x, x]), bad), n_policy=8)
    assert len(s["plan_fwd_bias"]) == 8 and s["plan_fwd_bias"][-1] < 0 and len(s["fwd_bias_policy"]) == 8


def test_along_reads_what_a_model_predicts_of_a_sequence_against_the_truth():
    """``model_check.along``: each sequence's signals averaged over the horizon on the model's
    rollout and the truth's, and its cost on each; a model that misses a constant push reads
    slower by the push's mean build-up, and each side starts from its own state."""
    from stride_jax.control import model_check

    dt, H = 0.1, 4
    truth = lambda q, qd, u, k: (q + dt * qd, qd + dt * u + 0.2)  # a push the model lacks
    model = lambda q, qd, u, k: (q + dt * qd, qd + dt * u)
    cost = lambda q, qd, u, t: jnp.sum(qd ** 2)
    value = lambda q, qd: q[0]
    signals = lambda q, qd: jnp.stack([qd[0], q[0]])
    seqs = jnp.stack([jnp.ones((H, 1)), -jnp.ones((H, 1))])
    q, qd = jnp.zeros(1), jnp.zeros(1)
    got = model_check.along(model, truth, cost, value, signals, seqs, q, q + 1.0, qd,
                            jax.random.key(0))
    track, c = np.asarray(got["track"]), np.asarray(got["cost"])
    assert track.shape == (2, 2, 2) and c.shape == (2, 2)
    # the truth's speed runs ahead by 0.2 per step: 0.2 * (1 + 2 + 3 + 4) / 4 on the mean
    np.testing.assert_allclose(track[:, 1, 0] - track[:, 0, 0], 0.5, atol=1e-6)
    np.testing.assert_allclose(track[0, 0, 0], dt * (1 + 2 + 3 + 4) / 4, atol=1e-6)
    assert track[0, 1, 1] > track[0, 0, 1] + 1.0 - 1e-6  # the truth starts 1 further on
    # the cost: each step's speed before it squared, summed, minus the end position (the value):
    # by hand, 0.14 - 0.06 and 0.14 + 0.06 on the model; 1.26 - 1.18 and 0.14 - 1.06 on the truth
    np.testing.assert_allclose(c, [[0.08, 0.08], [0.20, -0.92]], atol=1e-5)
    np.testing.assert_allclose(got["value"], [[0.06, 1.18], [-0.06, 1.06]], atol=1e-5)
    # the end states, whose value that is
    np.testing.assert_allclose(got["end_q"][..., 0], got["value"], atol=1e-6)
    np.testing.assert_allclose(got["end_qd"][:, 0, 0], [0.4, -0.4], atol=1e-6)


def test_a_policy_family_finds_the_command_offset_its_policy_lacks():
    """Candidates from a family of policies (the closed loop's PPO policy given command + z):
    a P-controller towards 1 under a drift settles at 0.5; the planner, searching z with the
    offsets warm-started across steps, asks it for ~1.5 and reaches the target."""
    drift = lambda q, qd, u, key=None: (q + u - 0.5, qd)
    family = lambda q, qd, z: (1.0 + z) - q
    policy = lambda q, qd: family(q, qd, jnp.zeros(1))
    cost = lambda q, qd, u, t: (q[0] - 1.0) ** 2
    cfg = mppi.MPPIConfig(samples=64, horizon=4, family_samples=56, policy_samples=8,
                          family_std=(0.3,), family_range=2.0, temperature=0.1)
    planner = mppi.make(cfg, drift, cost, [-5.0], [5.0], policy=policy, family=family)

    def run(planned: bool):
        def body(carry, _):
            q, state = carry
            if planned:
                u, state, _ = planner.step(state, q, jnp.zeros(1))
            else:
                u = policy(q, None)
            q, _ = drift(q, None, u)
            return (q, state), q[0]
        init = (jnp.zeros(1), planner.init(jax.random.key(0)))
        (q, state), qs = jax.lax.scan(body, init, None, length=40)
        return qs, state

    qs_policy = np.asarray(jax.jit(lambda: run(False))()[0])
    qs, state = jax.jit(lambda: run(True))()
    qs = np.asarray(qs)
    assert abs(qs_policy[-1] - 0.5) < 1e-5  # the policy alone keeps its offset
    assert np.abs(qs[-10:] - 1.0).max() < 0.1
    assert float(state.z[0]) == pytest.approx(0.5, abs=0.15)
    # a prior on the offsets that outweighs the gain keeps the plain policy
    costly = mppi.make(dataclasses.replace(cfg, family_cost=100.0), drift, cost, [-5.0], [5.0],
                       policy=policy, family=family)
    state = costly.init(jax.random.key(0))
    q = jnp.full(1, 0.5)
    for _ in range(5):
        u, state, _ = jax.jit(costly.step)(state, q, jnp.zeros(1))
    assert abs(float(state.z[0])) < 0.1
    with pytest.raises(ValueError, match="needs a family"):
        mppi.make(cfg, drift, cost, [-5.0], [5.0], policy=policy)
    with pytest.raises(ValueError, match="family_samples=60"):
        mppi.MPPIConfig(samples=64, policy_samples=8, family_samples=60)
    with pytest.raises(ValueError, match="family_decay"):
        mppi.MPPIConfig(family_decay=1.5)


def test_a_state_dependent_family_prior_prices_offsets_only_where_it_acts():
    """``family_prior(q, qd)`` adds to the offsets' prior where the state asks for it (the
    closed loop's stop command): the same planner finds the drift's offset where the prior is
    off and keeps the plain policy where it is on."""
    drift = lambda q, qd, u, key=None: (q + u - 0.5, qd)
    family = lambda q, qd, z: (1.0 + z) - q
    policy = lambda q, qd: family(q, qd, jnp.zeros(1))
    cost = lambda q, qd, u, t: (q[0] - 1.0) ** 2
    prior = lambda q, qd: 100.0 * qd[0]  # qd[0]: a flag the task carries (1: a stop)
    cfg = mppi.MPPIConfig(samples=64, horizon=4, family_samples=56, policy_samples=8,
                          family_std=(0.3,), family_range=2.0, temperature=0.1)
    planner = mppi.make(cfg, drift, cost, [-5.0], [5.0], policy=policy, family=family,
                        family_prior=prior)
    step = jax.jit(planner.step)
    z = {}
    for flag in (0.0, 1.0):
        state, q = planner.init(jax.random.key(0)), jnp.full(1, 0.5)
        for _ in range(8):
            _, state, _ = step(state, q, jnp.full(1, flag))
        z[flag] = float(state.z[0])
    assert z[0.0] > 0.3 and abs(z[1.0]) < 0.1, z
    with pytest.raises(ValueError, match="family_prior"):
        mppi.make(dataclasses.replace(cfg, family_samples=0, policy_samples=0), drift, cost,
                  [-5.0], [5.0], family_prior=prior)


def test_distrust_hands_the_action_to_the_policy_and_keeps_the_plan_warm():
    """While ``distrust`` holds (and ``distrust_hold`` steps after) the step applies the policy's
    action (clipped to the bounds) and says DISTRUSTED, but plans as without it: the same plan
    is kept for when trust returns. A gate that never fires changes nothing; no policy, no gate."""
    drift = lambda q, qd, u, key=None: (q + 0.1 * u, qd + 1.0)  # qd counts the steps
    cost = lambda q, qd, u, t: (q[0] - 1.0) ** 2
    policy = lambda q, qd: jnp.full(1, -3.0)  # beyond the bound of 2: clipped
    cfg = mppi.MPPIConfig(samples=64, horizon=5, noise_std=0.5, temperature=0.1,
                          distrust_hold=2)

    def run(distrust, n=5):
        planner = mppi.make(cfg, drift, cost, [-2.0], [2.0], policy=policy, distrust=distrust)
        step, state = jax.jit(planner.step), planner.init(jax.random.key(0))
        q, qd, out = jnp.zeros(1), jnp.zeros(1), []
        for _ in range(n):
            u, state, info = step(state, q, qd)
            out.append((float(u[0]), int(info.status), np.asarray(state.plan)))
            q, qd = drift(q, qd, jnp.asarray(state.plan[0]))  # the plan moves the state alike
        return out

    free = run(None)
    quiet = run(lambda q, qd: qd[0] > 99.0)
    gated = run(lambda q, qd: qd[0] < 0.5)  # the first step only, then held for two
    assert [(u, s) for u, s, _ in quiet] == [(u, s) for u, s, _ in free]
    assert [s for _, s, _ in gated] == [mppi.DISTRUSTED] * 3 + [mppi.PLANNED] * 2
    assert [u for u, _, _ in gated[:3]] == [-2.0] * 3  # the policy's action, clipped
    assert [u for u, _, _ in gated[3:]] == [u for u, _, _ in free[3:]]
    for (_, _, p_gated), (_, _, p_free) in zip(gated, free):
        np.testing.assert_array_equal(p_gated, p_free)  # planned as if trusted
    with pytest.raises(ValueError, match="distrust needs a policy"):
        mppi.make(cfg, drift, cost, [-2.0], [2.0], distrust=lambda q, qd: True)
    with pytest.raises(ValueError, match="distrust_hold"):
        mppi.MPPIConfig(distrust_hold=-1)


def test_a_delayed_gate_plans_through_a_brief_trigger_and_hands_over_a_lasting_one():
    """``distrust_after``: the gate hands the robot to the policy only once ``distrust`` has
    held that many steps in a row. A trigger of two steps (a push) is planned through; one of
    four hands over from its third step, held ``distrust_hold`` steps after; a gap resets the
    count; a state that is not finite leaves it; 0 and 1 hand over at once."""
    drift = lambda q, qd, u, key=None: (q + 0.1 * u, qd + 1.0)  # qd counts the steps
    cost = lambda q, qd, u, t: (q[0] - 1.0) ** 2
    policy = lambda q, qd: jnp.full(1, -3.0)
    base = mppi.MPPIConfig(samples=16, horizon=3, noise_std=0.5, distrust_hold=1)

    def statuses(after, steps_on, n=10, bad=()):
        cfg = dataclasses.replace(base, distrust_after=after)
        on = jnp.asarray([k in steps_on for k in range(n + 1)])
        planner = mppi.make(cfg, drift, cost, [-2.0], [2.0], policy=policy,
                            distrust=lambda q, qd: on[jnp.clip(qd[0].astype(int), 0, n)])
        step, state = jax.jit(planner.step), planner.init(jax.random.key(0))
        out = []
        for k in range(n):
            q = jnp.full(1, jnp.nan) if k in bad else jnp.zeros(1)
            _, state, info = step(state, q, jnp.full(1, float(k)))
            out.append("D" if int(info.status) == mppi.DISTRUSTED else
                       "B" if int(info.status) == mppi.BAD_STATE else ".")
        return "".join(out)

    assert statuses(3, {2, 3}) == ".........."  # two steps: planned through
    assert statuses(3, {2, 3, 4, 5}) == "....DDD..."  # from the third step on, held one after
    assert statuses(3, {1, 2, 4, 5, 6}) == "......DD.."  # the gap at 3 starts the count again
    assert statuses(3, {2, 4, 5}, bad={3}) == "...B.DD..."  # a bad state: neither count nor reset
    assert statuses(0, {2, 3}) == statuses(1, {2, 3}) == "..DDD....."  # at once, as before
    assert mppi.make(base, drift, cost, [-2.0], [2.0], policy=policy,
                     distrust=lambda q, qd: True).init(jax.random.key(0)).streak is None
    with pytest.raises(ValueError, match="distrust_after=3 delays the trust gate"):
        mppi.make(dataclasses.replace(base, distrust_after=3), drift, cost, [-2.0], [2.0])
    with pytest.raises(ValueError, match="distrust_after"):
        mppi.MPPIConfig(distrust_after=-1)


def test_an_alarm_swaps_the_policy_prior_for_wide_noise_around_the_plan():
    """A policy that always pushes the wrong way: its prior candidates pull the plan towards
    it. While the alarm holds, those candidates leave the policy (the plan plus noise at
    ``alarm_noise_std``) and the plan turns the right way; an alarm that never fires plans
    exactly as no alarm at all, and the step says which candidates planned."""
    drift = lambda q, qd, u, key=None: (q + 0.1 * u, qd)
    cost = lambda q, qd, u, t: (q[0] - 1.0) ** 2  # the target lies at +1
    wrong = lambda q, qd: jnp.full(1, -1.0)
    base = mppi.MPPIConfig(samples=64, horizon=5, noise_std=0.05, prior_fraction=1.0,
                           prior_noise_std=0.05, temperature=0.1)
    q0, qd0 = jnp.zeros(1), jnp.zeros(1)

    def plan(cfg, alarm=None):
        planner = mppi.make(cfg, drift, cost, [-2.0], [2.0], policy=wrong, alarm=alarm)
        u, state, info = jax.jit(planner.step)(planner.init(jax.random.key(0)), q0, qd0)
        return float(u[0]), info

    u_prior, info = plan(base)
    assert u_prior < -0.8 and not bool(info.alarm)  # the prior's candidates all follow the policy
    wide = dataclasses.replace(base, alarm_noise_std=1.0)
    u_quiet, info = plan(wide, alarm=lambda q, qd: q[0] > 5.0)
    assert u_quiet == u_prior and not bool(info.alarm)
    u_alarm, info = plan(wide, alarm=lambda q, qd: q[0] < 0.5)
    assert u_alarm > 0.3 and bool(info.alarm)
    with pytest.raises(ValueError, match="alarm_noise_std=1.0 needs an alarm"):
        mppi.make(wide, drift, cost, [-2.0], [2.0], policy=wrong)
    with pytest.raises(ValueError, match="alarm_noise_std"):
        mppi.MPPIConfig(alarm_noise_std=-0.1)
    with pytest.raises(ValueError, match="not on policy_noise"):
        mppi.MPPIConfig(policy_noise=True, alarm_noise_std=0.5)


def test_a_held_alarm_keeps_the_recovery_candidates_for_its_steps_after_it_last_rang():
    """``alarm_hold``: once the alarm has rung, the recovery candidates plan that many more
    steps after it stops (``Info.alarm`` says so); a new ring restarts the count; without a
    hold they plan only while it rings; a non-finite state leaves the count alone."""
    drift = lambda q, qd, u, key=None: (q + 0.1 * u, qd)
    cost = lambda q, qd, u, t: (q[0] - 1.0) ** 2
    wrong = lambda q, qd: jnp.full(1, -1.0)
    cfg = mppi.MPPIConfig(samples=16, horizon=3, noise_std=0.05, prior_fraction=1.0,
                          alarm_noise_std=1.0)
    ringing = lambda q, qd: q[0] < 0.0  # the tests' states: -1 rings, +1 is quiet

    def alarms(hold, states):
        planner = mppi.make(dataclasses.replace(cfg, alarm_hold=hold), drift, cost, [-2.0],
                            [2.0], policy=wrong, alarm=ringing)
        state, step, out = planner.init(jax.random.key(0)), jax.jit(planner.step), []
        for x in states:
            _, state, info = step(state, jnp.full(1, x), jnp.zeros(1))
            out.append(bool(info.alarm))
        return out

    quiet_after = [-1.0, 1.0, 1.0, 1.0, 1.0]
    assert alarms(0, quiet_after) == [True, False, False, False, False]
    assert alarms(2, quiet_after) == [True, True, True, False, False]
    assert alarms(2, [-1.0, 1.0, -1.0, 1.0, 1.0, 1.0]) == [True, True, True, True, True, False]
    assert alarms(2, [-1.0, float("nan"), 1.0, 1.0, 1.0]) == [True, True, True, True, False]
    with pytest.raises(ValueError, match="alarm_hold"):
        mppi.MPPIConfig(alarm_hold=-1)
