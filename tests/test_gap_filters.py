"""Cleaning and estimation on logs: resampling onto the control grid, noise level, Savitzky-Golay
derivatives and pass band, outlier and spike removal."""

import numpy as np

from stride_jax.gap import filters, logs


def test_resample_holds_commands_and_interpolates_states():
    t = np.array([0.0, 0.013, 0.021, 0.034, 0.04])
    q = t[:, None] * 2.0
    tr = logs.Trajectory("x", t, q, q.copy(), np.arange(5.0)[:, None], None, None)
    out = filters.resample(tr, 0.01)
    np.testing.assert_allclose(out.t, [0, 0.01, 0.02, 0.03, 0.04])
    np.testing.assert_allclose(out.q[:, 0], 2 * out.t, atol=1e-12)  # linear signal: exact
    np.testing.assert_array_equal(out.cmd[:, 0], [0, 0, 1, 2, 4])  # zero-order hold


def test_estimation_helpers():
    rng = np.random.default_rng(0)
    dt = 0.01
    t = np.arange(400) * dt
    x = np.sin(2 * np.pi * 1.0 * t)[:, None]
    noisy = x + 0.01 * rng.standard_normal(x.shape)
    assert abs(filters.noise_std(noisy)[0] - 0.01) < 0.003
    d = filters.savgol(noisy, dt, 21, 3, deriv=1)
    assert np.abs(d[20:-20, 0] - 2 * np.pi * np.cos(2 * np.pi * t[20:-20])).max() < 0.3
    assert filters.savgol_bandwidth(dt, 21) < filters.savgol_bandwidth(dt, 7) < 0.5 / dt
    spiky = x.copy()
    spiky[100] += 5.0
    clean, mask = filters.hampel(spiky)  # replaced by the window's median: off by the local slope
    assert mask[100, 0] and mask.sum() == 1 and abs(clean[100, 0] - x[100, 0]) < 0.1
    clean, mask = filters.spikes(spiky)
    assert mask[100, 0] and mask.sum() == 1 and abs(clean[100, 0] - x[100, 0]) < 0.05
    step = np.concatenate([np.zeros(50), np.ones(50)])[:, None]  # an impact: kept
    assert not filters.spikes(step)[1].any()
