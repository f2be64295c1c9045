"""Simulation-extrapolation (SIMEX, Cook and Stefanski 1994) of a bias that sensor noise in the
logged velocities would put into a fitted effect: an experiment's tool, not part of a diagnosis.

A k-step replay starts from the logged state, so the velocity noise enters the replay's start as
well as its target (errors in variables), which can bias an estimate by an amount that grows with
the noise's variance. The hypothesis it was built to test: that this is why noisy pendulum damping
(0.3, 8 x 150 steps) is fitted +0.9 standard errors high, its 90% interval covering the truth in
82% of draws (``results/gap_coverage/long``). Session 53's run (``results/gap_coverage/long_simex``)
said no (a flat path, coverage 28%); session 55 measured yes: the offset is the joint velocity
noise alone and grows with its variance (``results/gap_coverage/noise_terms``), and at the code
since ``fit.REFINE`` the refits rise with the added noise; with ``degree=1`` the correction
removes the offset (median 0.2999 for 0.3, ``results/gap_coverage/long_simex_line``), the
quadratic part of it (0.3013). The diagnosis has no SIMEX option yet (the offset is 0.6% of the
value at a real Go1's noise).

SIMEX measures that bias on the logs themselves: the fit is repeated with extra white noise of
variance ``lambda sigma^2`` added to the logged velocities (``sigma``: the logs' own noise level per
channel, :func:`velocity_noise`), for a few ``lambda``; the estimate's mean at each level, with the
plain estimate at ``lambda = 0``, is fitted by a quadratic in ``lambda`` and read at ``lambda =
-1``, where the noise's variance would be zero. The interval is moved with the estimate (its
width is the sampling spread, which the extra noise does not estimate) and clipped to the bounds.

What it assumes: the noise is white and additive in the velocities at the log's rate (what
:func:`stride_jax.gap.filters.noise_std` measures, from second differences: an upper bound where
the motion itself has large second differences, which then over-corrects); positions' noise is
left alone (encoders: 1e-4 rad against velocity estimates' 1e-2 rad/s). It costs
``draws x len(levels)`` refits of the effect.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np

from stride_jax.gap import filters
from stride_jax.gap.fit import Data


@dataclasses.dataclass(frozen=True)
class SimexConfig:
    """Attributes:
      draws: refits per noise level (0: no correction).
      levels: the added noise variances, in units of the logs' own (``lambda``).
      seed: of the added noise.
      degree: of the extrapolant in ``lambda``: 2 (Cook and Stefanski's quadratic) or 1 (a line:
        the errors-in-variables bias of a k-step replay grows with the noise's variance, i.e.
        linearly in ``lambda``, measured on the pendulum's damping in session 55; a line's
        extrapolation to -1 has a fraction of the quadratic's variance).
    """

    draws: int = 4
    levels: tuple[float, ...] = (0.5, 1.0, 1.5, 2.0)
    seed: int = 0
    degree: int = 2

    def __post_init__(self):
        if self.draws < 0:
            raise ValueError(f"draws={self.draws} must be >= 0")
        if self.degree not in (1, 2):
            raise ValueError(f"degree={self.degree}: the extrapolant is a line (1) or a quadratic (2)")
        if len(self.levels) < 2 or min(self.levels) <= 0:
            raise ValueError(f"levels={self.levels}: at least two, each > 0 (variances added in "
                             f"units of the logs' own)")


def velocity_noise(data: Data) -> np.ndarray:
    """``[nv]`` white-noise level of the logged velocities: per channel, the median over the
    trajectories of :func:`stride_jax.gap.filters.noise_std`."""
    b = data.bounds
    per = [filters.noise_std(data.qd[b[i]:b[i + 1]]) for i in range(len(b) - 1) if b[i + 1] - b[i] >= 3]
    if not per:
        raise ValueError("velocity_noise: every trajectory is shorter than 3 samples")
    return np.median(np.stack(per), axis=0)


def with_noise(data: Data, sd: np.ndarray, level: float, rng: np.random.Generator) -> Data:
    """``data`` with white noise of std ``sqrt(level) * sd [nv]`` added to its velocities (the
    replays' starts and targets alike)."""
    sd = np.asarray(sd, float)
    if sd.shape != (data.qd.shape[1],):
        raise ValueError(f"sd has shape {sd.shape}; the velocities have {data.qd.shape[1]} channels")
    qd = data.qd + np.sqrt(level) * sd * rng.standard_normal(data.qd.shape)
    return data._replace(qd=qd, target=qd[data.start + data.k])


def extrapolate(levels: np.ndarray, values: np.ndarray, degree: int = 2) -> np.ndarray:
    """The polynomial of ``degree`` (at most 2) in ``lambda`` through (least squares) ``values
    [L, p]`` at ``levels [L]``, read at ``lambda = -1`` (a line where only two levels are given)."""
    levels, values = np.asarray(levels, float), np.asarray(values, float)
    deg = min(degree, len(levels) - 1)
    A = np.vander(levels, deg + 1)
    coef, *_ = np.linalg.lstsq(A, values.reshape(len(levels), -1), rcond=None)
    return (np.vander(np.array([-1.0]), deg + 1) @ coef)[0].reshape(values.shape[1:])


def correct(refit: Callable[[Data], dict], data: Data, estimate: dict, cfg: SimexConfig,
            sd: np.ndarray | None = None) -> tuple[dict, dict]:
    """SIMEX-corrected values of ``estimate`` (name -> vector), the fit on ``data``.

    ``refit(data) -> {name: vector}`` repeats that fit on noisier data (``draws`` times per
    level); ``sd [nv]``: the logs' velocity noise (default :func:`velocity_noise`). Returns
    ``(corrected, path)``: the corrected values, and the path (``levels``, per name the mean
    estimate at each level, ``sd``) for the report."""
    if cfg.draws == 0:
        return dict(estimate), {}
    sd = velocity_noise(data) if sd is None else np.asarray(sd, float)
    rng = np.random.default_rng(cfg.seed)
    means = {n: [np.asarray(v, float)] for n, v in estimate.items()}
    for level in cfg.levels:
        got = [refit(with_noise(data, sd, level, rng)) for _ in range(cfg.draws)]
        for n in means:
            means[n].append(np.mean([np.asarray(g[n], float) for g in got], axis=0))
    levels = np.array((0.0,) + tuple(cfg.levels))
    corrected = {n: extrapolate(levels, np.stack(m), cfg.degree) for n, m in means.items()}
    path = {"levels": levels.tolist(), "sd": sd.tolist(),
            "means": {n: np.stack(m).tolist() for n, m in means.items()}}
    return corrected, path


def shifted(est: dict, lo: dict, hi: dict, corrected: dict, bounds: dict) -> tuple[dict, dict, dict]:
    """The estimate replaced by ``corrected`` and its interval moved with it, all clipped to
    ``bounds`` (name -> (lo [p], hi [p])); the interval still contains the estimate."""
    out_e, out_l, out_h = {}, {}, {}
    for n, x in est.items():
        b_lo, b_hi = (np.asarray(b, float) for b in bounds[n])
        c = np.clip(np.asarray(corrected[n], float), b_lo, b_hi)
        move = c - np.asarray(x, float)
        out_e[n] = c
        out_l[n] = np.minimum(np.clip(np.asarray(lo[n], float) + move, b_lo, b_hi), c)
        out_h[n] = np.maximum(np.clip(np.asarray(hi[n], float) + move, b_lo, b_hi), c)
    return out_e, out_l, out_h
