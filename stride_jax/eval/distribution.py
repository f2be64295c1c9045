"""Scores of a predicted distribution of futures, not of one sample.

A model's ``S`` sampled rollouts of a window are points ``x_s`` and the true futures ``y_k``
(the logged one, and with :mod:`stride_jax.sim.continuations` more, re-simulated under new draws
of the hidden randomness) points of the same space: the window's ``H`` steps of the normalised
observation error of ``eval/rollout.py`` (``[H, D]``, ``D = 2 nv``, relative to the logged
future, so the logged future is 0). Per window:

* **mean-of-samples error**: the cumulative per-horizon RMSE of the samples' mean (what a
  planner averaging samples sees), beside the per-sample error of Table I;
* **energy score** (Gneiting & Raftery, 2007), a proper score of the joint distribution over the
  whole window: ``ES = mean_{s,k} |x_s - y_k| - mean_{s != s'} |x_s - x_s'| / 2`` with ``|.|``
  the RMS over the window's ``H * D`` entries (so a deterministic model's score is its RMS
  error; lower is better; the unbiased "fair" form, Ferro 2014);
* **CRPS**: the same score per entry (a marginal proper score), averaged over entries;
* **coverage**: the share of true entries inside the samples' range (min to max). For a
  calibrated model ``S`` exchangeable samples bracket a new draw with probability
  ``(S - 1) / (S + 1)``, the interval's nominal level (90% at ``S = 19``); a deterministic model
  covers nothing.

Averages over windows (and true futures) are returned; all inputs are numpy.
"""

from __future__ import annotations

import numpy as np


def nominal_coverage(samples: int) -> float:
    """The probability that ``samples`` exchangeable draws bracket one more."""
    return (samples - 1) / (samples + 1)


def _pairwise_rms(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """RMS distance ``[..., A, B]`` between rows of ``a [..., A, F]`` and ``b [..., B, F]``."""
    d2 = (np.sum(a ** 2, -1)[..., :, None] + np.sum(b ** 2, -1)[..., None, :]
          - 2.0 * a @ np.swapaxes(b, -1, -2))
    return np.sqrt(np.maximum(d2, 0.0) / a.shape[-1])


def scores(samples: np.ndarray, truths: np.ndarray | None = None) -> dict:
    """Distribution scores of predicted windows.

    ``samples [S, N, H, D]``: normalised errors of ``S`` sampled rollouts of ``N`` windows
    against the logged future; ``truths [N, K, H, D]``: further true futures in the same
    coordinates (``None``: the logged one alone, which is 0). Non-finite samples (diverged
    rollouts) make their window's scores NaN and are counted in ``diverged``.
    """
    s, n, h, d = samples.shape
    if truths is None:
        truths = np.zeros((n, 1, h, d), samples.dtype)
    if truths.shape[0] != n or truths.shape[2:] != (h, d):
        raise ValueError(f"truths {truths.shape} do not match samples {samples.shape} "
                         "([N, K, H, D] against [S, N, H, D])")
    x = np.moveaxis(samples, 0, 1).astype(np.float64)  # [N, S, H, D]
    y = truths.astype(np.float64)
    ok = np.isfinite(x).all((1, 2, 3))
    x, y = x[ok], y[ok]
    if not len(x):  # every window diverged in some sample: nothing to score
        nan = float("nan")
        return {"energy": nan, "crps": nan, "coverage": nan, "mean_of_samples": nan,
                "nominal_coverage": nominal_coverage(s) if s > 1 else 0.0,
                "truths": int(y.shape[1]), "samples": int(s), "diverged": 1.0}
    flat = lambda a: a.reshape(a.shape[0], a.shape[1], -1)
    to_truth = _pairwise_rms(flat(x), flat(y)).mean((1, 2))
    spread = _pairwise_rms(flat(x), flat(x)).sum((1, 2)) / max(s * (s - 1), 1)
    energy = to_truth - 0.5 * spread
    # CRPS per entry, over windows: E|x - y| - E|x - x'| / 2 (fair form).
    abs_truth = np.abs(x[:, :, None] - y[:, None]).mean((1, 2))  # [N, H, D]
    xs = np.sort(x, axis=1)
    # sum_{s, s'} |x_s - x_s'| = 2 sum_i (2 i - S + 1) x_(i), i = 0..S-1, for sorted samples.
    weights = (2 * np.arange(s) - s + 1).reshape(1, s, 1, 1)
    pair_sum = 2.0 * np.sum(weights * xs, axis=1)
    crps = abs_truth - 0.5 * pair_sum / max(s * (s - 1), 1)
    lo, hi = xs[:, 0], xs[:, -1]
    inside = (y >= lo[:, None]) & (y <= hi[:, None]) & (s > 1)
    mean_err = np.sqrt(np.mean((x.mean(1)[:, None] - y) ** 2, -1)).sum(-1).mean(-1)  # [N]
    return {"energy": float(energy.mean()), "crps": float(crps.mean()),
            "coverage": float(inside.mean()),
            "nominal_coverage": nominal_coverage(s) if s > 1 else 0.0,
            "mean_of_samples": float(mean_err.mean()),
            "truths": int(y.shape[1]), "samples": int(s),
            "diverged": float(1.0 - ok.mean())}
