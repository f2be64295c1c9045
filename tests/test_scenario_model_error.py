"""experiments/scenario_model_error.py: a model's one-period error per phase of an episode."""

import numpy as np
import pytest


def test_phase_errors_split_a_steady_bias_from_what_varies(experiment):
    """A constant offset is the bias (what the planner's observer absorbs), a zero-mean
    alternation is the spread; the residual draws are averaged per step first."""
    mod = experiment("scenario_model_error")
    T, draws, nv, nu = 40, 3, 8, 2
    steady = np.array([-2.0, 0.0, 1.5])
    wiggle = np.where(np.arange(T) % 2 == 0, 1.0, -1.0)[:, None] * np.array([0.0, 0.3, 0.0])
    noise = np.random.default_rng(0).normal(size=(T, draws, 3))
    noise -= noise.mean(axis=1, keepdims=True)  # the draws disagree, their mean does not move
    acc = steady + wiggle[:, None, :] + noise
    qd = np.zeros((T, draws, nv))
    qd[..., -nu:] = 0.2
    got = mod.phase_errors(acc, qd, nu)
    np.testing.assert_allclose(got["bias"], steady, atol=1e-12)
    np.testing.assert_allclose(got["spread"], [0.0, 0.3, 0.0], atol=1e-12)
    assert got["bias_norm"] == pytest.approx(2.5) and got["steps"] == T
    assert got["joint_vel_rmse"] == pytest.approx(0.2)  # the base's entries left out


def test_bad_input_is_named(experiment, tmp_path):
    mod = experiment("scenario_model_error")
    with pytest.raises(SystemExit, match="expected NAME=RUN"):
        mod.main(["--models", "stride", "--out", str(tmp_path / "x")])
    with pytest.raises(SystemExit, match="no trained model there"):
        mod.main(["--models", f"stride={tmp_path}", "--out", str(tmp_path / "x")])
    with pytest.raises(SystemExit, match="--draws is 0"):
        mod.main(["--models", f"stride={tmp_path}", "--draws", "0", "--out", str(tmp_path / "x")])
    with pytest.raises(SystemExit, match="--nfe is -1"):
        mod.main(["--models", f"stride={tmp_path}", "--nfe", "-1", "--out", str(tmp_path / "x")])
    for bad, why in (("3,1.5", "ascending"), ("2,2", "ascending"), ("a", "comma-separated"),
                     (",", "ascending")):
        with pytest.raises(SystemExit, match=why):
            mod.main(["--models", f"stride={tmp_path}", "--split-s", bad, "--out", str(tmp_path / "x")])


def test_phases_cut_the_episode_at_each_split(experiment):
    """One split: before and from it (the labels the earlier reports carry); several: the
    stretches between them, every period in exactly one."""
    mod = experiment("scenario_model_error")
    t = np.arange(0, 6, 0.02)
    one = mod.phases(t, [2.0])
    assert list(one) == ["before 2 s", "from 2 s"]
    assert one["before 2 s"].sum() == 100 and one["from 2 s"].sum() == 200
    four = mod.phases(t, [1.5, 3.0, 4.5])
    assert list(four) == ["before 1.5 s", "1.5-3 s", "3-4.5 s", "from 4.5 s"]
    assert (np.sum(list(four.values()), axis=0) == 1).all()
    assert four["1.5-3 s"][np.searchsorted(t, 1.5)] and not four["1.5-3 s"][np.searchsorted(t, 3.0)]


def test_the_prior_alone_is_the_models_prior_term(experiment):
    """``prior_alone`` keeps the trained prior and leaves the residual force out: its
    acceleration is the model's own ``terms(...)['prior']``, not the full prediction; a model
    without a residual is refused by name."""
    import jax
    import jax.numpy as jnp

    import stride_jax.dynamics as dyn
    from stride_jax.dynamics import mlp, models, stride

    mod = experiment("scenario_model_error")
    spec = dyn.ModelSpec(nq=3, nv=3, floating_base=False)
    cfg = stride.StructuredConfig(net=mlp.MLPConfig(hidden=16, depth=2))
    model = models.make("delan", spec, None, cfg)
    params = model.init(jax.random.key(0))
    # a residual that pushes: the last layer is zero at init, so scale everything up
    params["residual"] = jax.tree.map(lambda w: w + 0.5, params["residual"])
    q, qd, tau = jnp.array([0.3, -0.2, 0.1]), jnp.array([0.5, 0.0, -0.4]), jnp.ones(3)
    prior, p_params = mod.prior_alone(model, params)
    got = prior.acceleration(p_params, q, qd, tau, None)
    split = model.terms(params, q, qd, tau, None)
    np.testing.assert_allclose(got, split["prior"], rtol=1e-5, atol=1e-6)
    assert float(jnp.abs(split["residual"]).max()) > 1e-2  # the full model differs
    with pytest.raises(ValueError, match="no residual"):
        mod.prior_alone(prior, p_params)


def test_the_scenario_takes_the_closed_loops_overrides_and_refuses_what_it_has_no_use_for(experiment):
    mod = experiment("scenario_model_error")
    sc = mod.scenario("rough", 3.0, rough_cm=2)
    assert (sc.name, sc.rough_m, sc.seconds) == ("rough2", pytest.approx(0.02), 3.0)
    sc = mod.scenario("tilt", 6.0, slope_deg=15)
    assert (sc.name, sc.slope_deg) == ("tilt15", 15)
    assert mod.scenario("walk", 6.0).name == "walk"
    with pytest.raises(SystemExit, match="'walk' has no rough ground"):
        mod.scenario("walk", 6.0, rough_cm=2)
    with pytest.raises(SystemExit, match="'rough' has no slope"):
        mod.scenario("rough", 6.0, slope_deg=15)
    with pytest.raises(SystemExit, match="'cliff': one of"):
        mod.scenario("cliff", 6.0)


def test_one_period_draws_the_residual_or_takes_its_central_sample(experiment):
    """Drawn rows: ``draws`` different residual samples per state; ``central``: one per state,
    the model's own step with no key (its latent at the centre)."""
    import jax

    import stride_jax.dynamics as dyn
    from stride_jax.control.episode import learned_step
    from stride_jax.dynamics import mlp, models, stride

    mod = experiment("scenario_model_error")
    spec = dyn.ModelSpec(nq=3, nv=3, floating_base=False)
    model = models.make("stride", spec, None,
                        stride.StructuredConfig(net=mlp.MLPConfig(hidden=16, depth=2)))
    params = model.init(jax.random.key(0))
    params["residual"] = jax.tree.map(lambda w: w + 0.3, params["residual"])  # a residual that varies
    rng = np.random.default_rng(0)
    q, qd, u = (rng.normal(size=(5, 3)).astype(np.float32) for _ in range(3))
    step = learned_step(model, params)
    drawn = mod.one_period(step, q, qd, u, None, 4)
    central = mod.one_period(step, q, qd, u, None, 4, central=True)
    assert drawn.shape == (5, 4, 3) and central.shape == (5, 1, 3)
    assert np.abs(drawn[:, 0] - drawn[:, 1]).max() > 1e-2
    own = jax.vmap(lambda a, b, c: model.step(params, a, b, c, None)[1])(q, qd, u)
    np.testing.assert_allclose(central[:, 0], np.asarray(own), rtol=1e-5, atol=1e-5)
