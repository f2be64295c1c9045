"""Distribution scores (eval/distribution.py) and true continuations (sim/continuations.py)."""

import jax
import numpy as np
import pytest

from stride_jax.eval import distribution
from stride_jax.sim import continuations, rollout_cpu


def test_a_point_prediction_scores_its_error():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(1, 20, 5, 4))  # one sample: a deterministic model
    d = distribution.scores(x)
    rms = np.sqrt((x[0].reshape(20, -1) ** 2).mean(-1)).mean()
    np.testing.assert_allclose(d["energy"], rms, rtol=1e-6)
    np.testing.assert_allclose(d["crps"], np.abs(x).mean(), rtol=1e-6)
    assert d["coverage"] == 0.0 and d["nominal_coverage"] == 0.0
    np.testing.assert_allclose(d["mean_of_samples"],
                               np.sqrt((x[0] ** 2).mean(-1)).sum(-1).mean(), rtol=1e-6)


def test_calibrated_samples_cover_at_the_nominal_level_and_score_best():
    rng = np.random.default_rng(1)
    n, k = 400, 4
    truths = rng.normal(size=(n, k, 3, 2))
    calibrated = rng.normal(size=(19, n, 3, 2))
    narrow = 0.2 * rng.normal(size=(19, n, 3, 2))
    wide = 3.0 * rng.normal(size=(19, n, 3, 2))
    good = distribution.scores(calibrated, truths)
    assert abs(good["coverage"] - 0.9) < 0.02 and good["nominal_coverage"] == 0.9
    assert distribution.scores(narrow, truths)["coverage"] < 0.5
    for other in (narrow, wide):  # a proper score prefers the true distribution
        d = distribution.scores(other, truths)
        assert good["energy"] < d["energy"] and good["crps"] < d["crps"]
    # The mean of many samples of the truth's distribution is near its centre.
    assert good["mean_of_samples"] < distribution.scores(calibrated[:1], truths)[
        "mean_of_samples"]


def test_diverged_windows_are_counted_not_scored():
    x = np.zeros((3, 4, 2, 2))
    x[1, 2, 1, 0] = np.nan
    d = distribution.scores(x)
    assert d["diverged"] == 0.25 and np.isfinite(d["energy"])


def test_all_windows_diverged_gives_nan_scores_not_an_error():
    samples = np.full((3, 4, 5, 19), np.inf)
    out = distribution.scores(samples, np.zeros((4, 9, 5, 19)))
    assert out["diverged"] == 1.0 and np.isnan(out["energy"]) and np.isnan(out["crps"])


def test_mismatched_truths_are_a_clear_error():
    with pytest.raises(ValueError, match="truths"):
        distribution.scores(np.zeros((3, 4, 2, 2)), np.zeros((5, 1, 2, 2)))


@pytest.fixture(scope="module")
def pendulum():
    from stride_jax.sim import model
    return model.load("pendulum")


def test_continuations_redraw_the_hidden_randomness(pendulum):
    sm = pendulum
    r = sm.robot.randomization
    q0 = np.array([[np.pi - 0.1], [0.5]])
    qd0 = np.array([[0.0], [1.0]])
    ctrls = np.zeros((2, 12, 1))
    t0 = np.array([0.0, 1.0])
    make = lambda seed: continuations.simulate(sm, r, q0, qd0, ctrls, t0, 5.0, 6,
                                               jax.random.key(seed), nthread=1)
    a, b = make(0), make(0)
    np.testing.assert_array_equal(a.q, b.q)  # reproducible from the key
    assert a.q.shape == (2, 6, 12, 1) and a.qd.shape == (2, 6, 12, 1) and a.valid.all()
    # Near the upright the hidden bump's sign differs between draws: the futures spread.
    assert np.ptp(a.q[0, :, -1, 0]) > 1e-2
    # Without randomisation every future is the nominal simulator's.
    nominal = continuations.simulate(sm, None, q0, qd0, ctrls, t0, 5.0, 3, jax.random.key(0),
                                     nthread=1)
    ref = rollout_cpu.simulate(sm, q0[0], qd0[0], np.zeros((13, 1)))
    np.testing.assert_allclose(nominal.q[0, 2], ref.q[1:], atol=1e-6)
    np.testing.assert_allclose(nominal.q[0, 0], nominal.q[0, 1])


def test_continuations_check_their_shapes(pendulum):
    with pytest.raises(ValueError, match="windows"):
        continuations.simulate(pendulum, None, np.zeros((2, 1)), np.zeros((3, 1)),
                               np.zeros((2, 4, 1)), np.zeros(2), 5.0, 2, jax.random.key(0))
