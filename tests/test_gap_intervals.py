"""Intervals of vector effects (``stride_jax.gap.intervals.vector_interval``) on a synthetic
objective whose truth is known: the sandwich where the loss is quadratic, widened by the paired
test along a component where the loss is rough."""

import numpy as np
from scipy.optimize import minimize

from stride_jax.gap import intervals

TRUTH = np.array([0.3, 0.1])


class Rough:
    """Residuals of a linear model in two parameters with noise, plus a term in the first
    parameter that flips sign on a fine scale (``rough`` > 0): local minima everywhere along it,
    as contacts make the Go1's centre-of-mass offset's loss; blocks of 10 samples."""

    def __init__(self, rough: float):
        rng = np.random.default_rng(0)
        self.u, self.w, self.e, self.s = rng.normal(size=(4, 400))
        self.e *= 0.3
        self.rough = rough
        self.ids, self.nb, self.unstable = np.arange(400) // 10, 40, 0
        self.nxt = np.where(np.arange(40) < 39, np.arange(1, 41), -1)

    def residual(self, p):
        r = (p[0] - TRUTH[0]) * self.u + (p[1] - TRUTH[1]) * self.w + self.e
        return (r + self.rough * np.sign(np.sin(400 * p[0])) * self.s)[:, None]

    def block_losses(self, p):
        return np.bincount(self.ids, weights=(self.residual(p) ** 2).sum(1), minlength=self.nb)

    def block_losses_many(self, ps):
        return np.stack([self.block_losses(p) for p in ps])


def _fit(obj):
    return minimize(lambda p: obj.block_losses(p).sum(), np.zeros(2), method="Nelder-Mead",
                    options=dict(xatol=1e-7, fatol=1e-10)).x


def test_a_smooth_vector_keeps_the_sandwich_a_rough_component_is_widened_to_the_truth():
    lo, hi = -np.ones(2), np.ones(2)
    smooth = Rough(0.0)
    x = _fit(smooth)
    sl, sh = intervals.sandwich(smooth, x, lo, hi, 0.9)
    vl, vh, info = intervals.vector_interval(smooth, x, lo, hi, 0.9)
    assert info["rough"] == [] and np.allclose(vl, sl) and np.allclose(vh, sh)
    assert np.all((vl <= TRUTH) & (TRUTH <= vh))

    rough = Rough(0.05)
    x = _fit(rough)  # stuck in a local minimum far from the truth's first component
    assert abs(x[0] - TRUTH[0]) > 0.1
    sl, sh = intervals.sandwich(rough, x, lo, hi, 0.9)
    assert not sl[0] <= TRUTH[0] <= sh[0]  # the sandwich misses it
    vl, vh, info = intervals.vector_interval(rough, x, lo, hi, 0.9)
    assert info["rough"] == [0]
    assert vl[0] <= TRUTH[0] <= vh[0] and vl[0] <= x[0] <= vh[0] and lo[0] <= vl[0] and vh[0] <= hi[0]
    assert (vl[1], vh[1]) == (sl[1], sh[1])  # the smooth component keeps its sandwich


def test_stencil_nodes_stay_distinct_and_inside_the_bounds_whatever_the_step():
    for x, h in [(0.5, 0.01), (0.0, 0.3), (1.0, 0.3), (0.02, 0.8), (0.5, 5.0), (0.0, 5.0), (1.0, 5.0)]:
        t = intervals._nodes(x, h, 0.0, 1.0)
        assert x in t and np.all(np.diff(t) > 0) and t[0] >= 0.0 and t[-1] <= 1.0, (x, h, t)
        d1, d2 = intervals._lagrange(t, x)
        assert np.all(np.isfinite(d1)) and np.all(np.isfinite(d2))
    assert np.allclose(intervals._nodes(0.5, 0.01, 0.0, 1.0), [0.49, 0.5, 0.51])  # the plain stencil


class Flat:
    """A scalar whose loss depends little on it (a wide interval), its minimum at 0.5 of [0, 1]:
    the 16x roughness check's step exceeds the bounds on both sides."""

    def __init__(self):
        rng = np.random.default_rng(1)
        self.u, self.e = rng.normal(size=(2, 400))
        self.e -= self.u * (self.u @ self.e) / (self.u @ self.u)  # the minimum exactly at 0.5
        self.ids, self.nb, self.unstable = np.arange(400) // 10, 40, 0
        self.nxt = np.where(np.arange(40) < 39, np.arange(1, 41), -1)

    def block_losses(self, p):
        r = 0.2 * (p[0] - 0.5) * self.u + self.e
        return np.bincount(self.ids, weights=r ** 2, minlength=self.nb)

    def block_losses_many(self, ps):
        return np.stack([self.block_losses(p) for p in ps])


def test_a_wide_scalar_interval_is_finite_and_checks_its_roughness_at_every_scale():
    import warnings
    obj = Flat()
    x = 0.5
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no division by zero in the stencil weights
        lo, hi, info = intervals.scalar_interval(obj, x, float(obj.block_losses([x]).sum()), 0.0, 1.0, 0.9)
    assert 0.0 <= lo <= x <= hi <= 1.0
    assert all(np.isfinite(v) for k, v in info.items() if k.startswith("curvature"))
