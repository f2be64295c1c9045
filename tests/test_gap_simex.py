"""SIMEX of the errors-in-variables bias (``stride_jax.gap.simex``) on cases whose truth is known."""

import numpy as np
import pytest

from stride_jax.gap import fit, logs, simex


def _data(qd: np.ndarray, k: int = 1) -> fit.Data:
    t = np.arange(len(qd), dtype=float)
    tr = logs.Trajectory("a", t, np.zeros((len(qd), 1)), qd[:, None], np.zeros((len(qd), 1)), None, None)
    return fit.make_data([tr], k)


def _slope(data: fit.Data) -> dict:
    """The least-squares AR(1) coefficient of the logged velocity: the target on the start."""
    x, y = data.qd[data.start, 0], data.target[:, 0]
    return {"b": np.array([x @ y / (x @ x)])}


def test_simex_removes_most_of_the_attenuation_of_a_noisy_regressor():
    """x_{t+1} = 0.9 x_t + w, logged with white noise of std 1: the plain fit of 0.9 is attenuated
    to ~0.76 (var x / (var x + 1)); SIMEX with the known noise level brings it within a third of
    that bias of the truth, and its path rises away from the truth as noise is added."""
    rng = np.random.default_rng(0)
    n, b = 40000, 0.9
    x = np.zeros(n)
    for t in range(1, n):
        x[t] = b * x[t - 1] + rng.standard_normal()
    data = _data(x + rng.standard_normal(n))
    naive = _slope(data)
    assert naive["b"][0] < b - 0.1
    cfg = simex.SimexConfig(draws=2, seed=1)
    corrected, path = simex.correct(_slope, data, naive, cfg, sd=np.ones(1))
    assert abs(corrected["b"][0] - b) < abs(naive["b"][0] - b) / 3
    means = np.asarray(path["means"]["b"])[:, 0]
    assert np.all(np.diff(means) < 0) and path["levels"][0] == 0.0
    # without noise in the logs there is nothing to correct: the path is flat at the truth
    clean = _data(x)
    c, _ = simex.correct(_slope, clean, _slope(clean), cfg, sd=np.zeros(1))
    assert c["b"][0] == pytest.approx(_slope(clean)["b"][0], abs=1e-12)


def test_extrapolation_and_the_moved_interval():
    """A quadratic path is read exactly at -1 (a line with two levels); the interval moves with
    the estimate, is clipped to the bounds and still contains the estimate."""
    lv = np.array([0.0, 0.5, 1.0, 2.0])
    np.testing.assert_allclose(simex.extrapolate(lv, (1 + 0.2 * lv + 0.05 * lv ** 2)[:, None]), [0.85])
    np.testing.assert_allclose(simex.extrapolate(lv[:2], (1 + 0.2 * lv[:2])[:, None]), [0.8])
    # degree 1: the least-squares line through the levels, read at -1 (a quadratic path's
    # curvature is then not followed: 0.85 exactly with degree 2, not with a line)
    line = 1 + 0.2 * lv
    np.testing.assert_allclose(simex.extrapolate(lv, line[:, None], degree=1), [0.8])
    assert simex.extrapolate(lv, (line + 0.05 * lv ** 2)[:, None], degree=1)[0] != pytest.approx(0.85)
    with pytest.raises(ValueError, match="degree=3"):
        simex.SimexConfig(degree=3)
    est, lo, hi = simex.shifted({"d": np.array([0.31])}, {"d": np.array([0.30])}, {"d": np.array([0.32])},
                                {"d": np.array([0.305])}, {"d": (np.array([0.0]), np.array([2.0]))})
    np.testing.assert_allclose([est["d"][0], lo["d"][0], hi["d"][0]], [0.305, 0.295, 0.315])
    est, lo, hi = simex.shifted({"d": np.array([0.01])}, {"d": np.array([0.0])}, {"d": np.array([0.03])},
                                {"d": np.array([-0.02])}, {"d": (np.array([0.0]), np.array([2.0]))})
    assert est["d"][0] == 0.0 and lo["d"][0] == 0.0 and hi["d"][0] == pytest.approx(0.02)  # moved by 0.01


def test_the_noise_level_and_bad_settings():
    """The logs' velocity noise is read per channel (white noise on a slow signal: within 10%);
    a wrong noise shape and bad settings are named."""
    rng = np.random.default_rng(2)
    t = np.linspace(0, 10, 2000)
    qd = np.stack([np.sin(t), np.cos(0.5 * t)], 1) + rng.standard_normal((2000, 2)) * [0.03, 0.1]
    tr = logs.Trajectory("a", t, np.zeros((2000, 2)), qd, np.zeros((2000, 2)), None, None)
    np.testing.assert_allclose(simex.velocity_noise(fit.make_data([tr, tr._replace(name="b")])),
                               [0.03, 0.1], rtol=0.1)
    with pytest.raises(ValueError, match="2 channels"):
        simex.with_noise(fit.make_data([tr]), np.ones(3), 1.0, rng)
    with pytest.raises(ValueError, match="levels"):
        simex.SimexConfig(levels=(1.0,))
    with pytest.raises(ValueError, match="draws=-1"):
        simex.SimexConfig(draws=-1)
