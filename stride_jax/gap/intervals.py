"""Intervals of fitted effect parameters (level ``FitConfig.level``) from per-block scores of the
training loss, as :mod:`stride_jax.gap.fit`'s docstring describes: the profile likelihood with a
sandwich-calibrated threshold for scalars, a paired per-block test for an integer (delay), for a
vector the hull of the sandwich and a paired test along each component, the sandwich covariance for
pairs; all clipped to the bounds, all containing the estimate.
``obj`` is a :class:`stride_jax.gap.fit.Objective`."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from scipy import stats

if TYPE_CHECKING:
    from stride_jax.gap.fit import Objective


KINK = 2.0  # curvature at the profile's step over that at 4x or 16x the step beyond which the loss is kinked
# or rough: 16x (8 sandwich half widths) because contacts make a legged robot's loss jagged at about
# the estimate's own spread, where a minimum's local curvature is several times the bowl's (Go1,
# torque_scale 0.65 in noise: 716k at the step, 871k at 4x, ~160k at 16x; the profile interval a
# fifth of the estimates' spread, 21/30 covered; experiments/gap_coverage.py --robot go1)
SCALES = (4, 16)
# fewer blocks than this moved by the parameter: its spread rests on a few events (a limit reached a few
# times), the sandwich's variance on fewer than 7 degrees of freedom; the interval is the test's
# (pendulum, torque_limit 0.7 in noise, 2-5 such blocks of 16: the sandwich covered 35% of draws)
MIN_BLOCKS = 8


def _quantile(level: float, nb: int) -> float:
    """Two-sided Student quantile for ``nb`` blocks."""
    return float(stats.t.ppf(0.5 + level / 2, max(nb - 1, 1)))


def _score_var(G: np.ndarray, nxt: np.ndarray) -> np.ndarray:
    """``[p, p]`` variance of the sum of per-block scores ``G [nb, p]`` (centred), with the
    covariance of neighbouring blocks of a trajectory (``nxt [nb]``, -1: none) at full weight.

    Full weight, not Newey-West's Bartlett 1/2: a k-step replay's target is the start of the
    replay k steps later, so each logged sample's noise enters two replays with opposite signs and
    nearly cancels in the sum; blocks of at least 2k steps keep those pairs within neighbouring
    blocks, and only the full lag-one covariance cancels them (measured on the pendulum, damping
    0.3 in noise, blocks of 10: Bartlett overestimated the variance 5x). Should the estimate not
    be positive definite, Bartlett's is used.
    """
    G = G - G.mean(0)
    V = G.T @ G
    ok = nxt >= 0
    C = G[ok].T @ G[nxt[ok]]
    nb = len(G)
    out = V + C + C.T
    if np.linalg.eigvalsh(out).min() <= 0:
        out = V + 0.5 * (C + C.T)
    return out * nb / max(nb - 1, 1)


def _not_worse(d: np.ndarray, nxt: np.ndarray, q: float) -> bool:
    """The one-sided paired per-block test: block loss differences ``d [nb]`` (a value's minus the
    estimate's) do not exceed ``q`` standard deviations of their sum (:func:`_score_var`)."""
    return float(d.sum()) <= q * np.sqrt(max(float(_score_var(d[:, None], nxt)[0, 0]), 0.0))


def _outward(ok, x: float, bound: float, step: float) -> tuple[float, float | None]:
    """Doubling steps from ``x`` towards ``bound`` (first ``step``) while ``ok(v)``: ``(inside,
    out)``, the last value accepted (``x`` if none) and the first rejected (None: none before
    the bound)."""
    inside = x
    while True:
        v = float(min(x + step, bound) if bound >= x else max(x - step, bound))
        if v == inside:
            return inside, None
        if not ok(v):
            return inside, v
        inside = v
        if v == bound:
            return inside, None
        step *= 2


def _rough(H: float, wide) -> bool:
    """The kink rule: the curvature ``H`` at the step is more than :data:`KINK` times one taken at
    :data:`SCALES` times it (``wide``), or one of those is not positive."""
    return any(Hk <= 0 or H > KINK * Hk for Hk in wide)


def _lagrange(t: np.ndarray, x: float) -> tuple[np.ndarray, np.ndarray]:
    """Weights of the first and second derivative at ``x`` of the parabola through nodes ``t [3]``."""
    d1, d2 = np.empty(3), np.empty(3)
    for i in range(3):
        j, k = [m for m in range(3) if m != i]
        den = (t[i] - t[j]) * (t[i] - t[k])
        d1[i] = ((x - t[j]) + (x - t[k])) / den
        d2[i] = 2 / den
    return d1, d2


def _nodes(x: float, h: float, lo: float, hi: float) -> np.ndarray:
    """``[3]`` distinct stencil nodes, ``x`` among them: ``x - h, x, x + h`` inside ``[lo, hi]``,
    one-sided (``x`` first or last) where a side would leave the bounds, and where the step does
    not fit the bounds at all (a wide interval's 16x check) the widest nodes that do: the bounds
    and ``x``, or ``x``, the midpoint and the far bound for ``x`` on a bound. (Clipped instead,
    two nodes met at a bound and the curvature came out infinite or NaN, which silently passed
    the roughness check.)"""
    t = np.array([x - h, x, x + h])
    if t[0] < lo:
        t = np.array([x, x + h, x + 2 * h])
    elif t[2] > hi:
        t = np.array([x - 2 * h, x - h, x])
    if t[0] >= lo and t[2] <= hi:
        return t
    if lo < x < hi:
        return np.array([lo, x, hi])
    far = hi if x <= lo else lo
    return np.array(sorted([x, (x + far) / 2, far]))


def _at_bound(x: np.ndarray, lo: np.ndarray, hi: np.ndarray, nominal) -> np.ndarray:
    """Whether each estimate sits on a bound that is not its nominal value (a nominal value on a
    bound, e.g. no delay, is an absent effect, not a truncated one)."""
    tol = 1e-3 * (hi - lo)
    nom = np.asarray(nominal, float)
    on = (x <= lo + tol) | (x >= hi - tol)
    return on & (np.abs(x - nom) > tol)


def scalar_interval(obj: Objective, x: float, f: float, lo: float, hi: float, level: float
                    ) -> tuple[float, float, dict]:
    """Interval of a continuous scalar at the estimate ``x`` (training loss ``f``): the profile.

    The set ``{v : L(v) - f <= c}`` around ``x``, ``c = t^2 V / (2 H)``: for a loss quadratic
    near ``x`` this is ``x +- t sqrt(V) / H``, the sandwich interval, and where the loss is not
    quadratic the profile bends it. ``V`` is the block variance of the loss gradient (central
    differences of the per-block losses), ``H`` the curvature. Clipped to ``[lo, hi]``; contains
    ``x`` by construction. A flat or concave profile (``H <= 0``) gives the bounds. The ends are
    bracketed by doubling steps from ``x`` and refined to 5% of the sandwich half width.

    Where the loss is kinked or rough at ``x`` -- its curvature at the step used is more than
    :data:`KINK` times that at four or sixteen times the step (:data:`SCALES`), as at a force limit
    or a dead band that few samples reach, or where contact events make the loss jagged at the
    estimate's own spread -- or the parameter moves the loss of fewer than :data:`MIN_BLOCKS` blocks,
    ``V`` and ``H`` say little about the spread of the estimate, and the interval is
    :func:`paired_interval`'s instead (``info["method"] == "test"``). In a block the parameter does
    not move at all nothing is learnt about it: Student's t and ``V``'s small-sample factor count
    the blocks it moves (``info["informative_blocks"]``); fewer than two give the bounds.
    """
    span = hi - lo
    total = lambda v: float(obj.block_losses(np.array([v])).sum())
    Lx = obj.block_losses(np.array([x]))

    def stencil(h: float) -> tuple[np.ndarray, np.ndarray]:  # nodes around x inside the bounds, [3, nb] losses
        t = _nodes(x, h, lo, hi)
        others = [v for v in t if v != x]
        Bo = iter(obj.block_losses_many([[v] for v in others]))
        return t, np.stack([Lx if v == x else next(Bo) for v in t])

    h, info = 0.01 * span, {}
    for _ in range(2):  # a second pass sizes the step to the interval
        t, B = stencil(h)
        d1, d2 = _lagrange(t, x)
        g = d1 @ B  # [nb] per-block gradient
        H = float(d2 @ B.sum(1))
        # blocks whose loss the parameter moves at all: an effect that acts in a few blocks only
        # (a limit reached a few times) has that many of them to estimate its spread from, and at
        # the optimum their gradients sum to zero -- with one such block V is 0 whatever the
        # spread. Student's t over those blocks, and V's small-sample factor over them.
        n_eff = int((np.abs(B - B[1]).max(0) > 1e-12 * max(float(np.abs(B).max()), 1e-300)).sum())
        if n_eff < 2:
            return lo, hi, {"method": "profile", "flat": True, "informative_blocks": n_eff}
        V = float(_score_var(g[:, None], obj.nxt)[0, 0]) * (obj.nb - 1) / obj.nb * n_eff / (n_eff - 1)
        if H <= 0 or V <= 0:
            return lo, hi, {"method": "profile", "flat": True, "informative_blocks": n_eff}
        half = _quantile(level, n_eff) * np.sqrt(V) / H
        new_h = float(np.clip(half / 2, 1e-4 * span, 0.05 * span))
        if 0.2 < new_h / h < 5:
            break
        h = new_h
    # is the loss quadratic near x? Its curvature at four and sixteen times the step must agree. A kink at the
    # estimate (a force limit or dead band that only a few samples reach) makes the curvature
    # grow without bound as the step shrinks, and the sandwich interval with it collapses
    # (pendulum, torque_limit 0.7 in noise: 35% coverage; experiments/gap_coverage.py)
    wide = {}
    for k in SCALES:
        tk, Bk = stencil(k * h)
        wide[f"curvature_{k}h"] = float(_lagrange(tk, x)[1] @ Bk.sum(1))
    if _rough(H, wide.values()) or n_eff < MIN_BLOCKS:
        a, b = paired_interval(obj, x, Lx, lo, hi, level, 4 * h, n_eff)
        return a, b, {"method": "test", "curvature": H, **wide, "sandwich_half_width": half,
                      "informative_blocks": n_eff}
    c = half ** 2 * H / 2
    info = {"method": "profile", "threshold": c, "sandwich_half_width": half, "curvature": H, **wide,
            "informative_blocks": n_eff}
    D = {}  # the profile above the minimum at the values tried

    def within(v: float) -> bool:
        D[v] = total(v) - f
        return D[v] <= c

    ends = []
    for bound in (lo, hi):
        # bracket the end, from a little past the sandwich end (brackets a quadratic profile)
        inside, v = _outward(within, x, bound, 1.2 * half)
        if v is None:
            ends.append(inside)
            continue
        # refine: the root of the parabola from x through the outer point (exact for a quadratic
        # profile), kept 10% inside the bracket (the profile need not be monotone), until the
        # profile there is within 10% of the threshold
        a, b, Db, end = inside, v, D[v], None
        for _ in range(4):
            m = x + (b - x) * np.sqrt(c / Db)
            m = float(np.clip(m, min(a, b) + 0.1 * abs(b - a), max(a, b) - 0.1 * abs(b - a)))
            Dm = total(m) - f
            if abs(Dm - c) <= 0.1 * c:
                end = m
                break
            if Dm > c:
                b, Db = m, Dm
            else:
                a = m
            if abs(b - a) <= 0.05 * half:
                break
        ends.append(float((a + b) / 2 if end is None else end))
    return min(ends[0], x), max(ends[1], x), info


def paired_interval(obj: Objective, x: float, Lx: np.ndarray, lo: float, hi: float, level: float,
                    step: float, n_eff: int | None = None) -> tuple[float, float]:
    """Interval of a scalar by test inversion: the values ``v`` that a one-sided paired per-block
    test at ``(1 - level) / 2`` does not find worse than the estimate ``x`` (per-block losses
    ``Lx``), as :func:`integer_set` for a delay. Each end is bracketed by doubling steps from
    ``x`` (first ``step``) and refined by four bisections; a value the logs cannot tell from ``x``
    (no block changes) stays inside. It needs no curvature, so it holds where the loss is kinked;
    where the loss is smooth it is about twice the sandwich interval. ``n_eff``: the blocks the
    parameter moves (Student's t over them; default all)."""
    q = _quantile(level, len(Lx) if n_eff is None else n_eff)

    accept = lambda v: _not_worse(obj.block_losses(np.array([v])) - Lx, obj.nxt, q)

    ends = []
    for bound in (lo, hi):
        inside, out = _outward(accept, x, bound, step)
        if out is not None:
            for _ in range(4):
                m = (inside + out) / 2
                if accept(m):
                    inside = m
                else:
                    out = m
        ends.append(inside)
    return min(ends[0], x), max(ends[1], x)


def integer_set(B: np.ndarray, xs: np.ndarray, k: int, nxt: np.ndarray, level: float
                ) -> tuple[float, float]:
    """Hull of the integer values ``xs [X]`` (per-block losses ``B [X, nb]``) that a one-sided
    paired test at ``(1 - level) / 2`` does not find worse than the estimate ``xs[k]``."""
    q = _quantile(level, B.shape[1])
    keep = []
    for j in range(len(xs)):
        dlt = B[j] - B[k]
        keep.append(j == k or _not_worse(dlt, nxt, q))
    ok = xs[np.array(keep)]
    return float(ok.min()), float(ok.max())


def sandwich(obj: Objective, x: np.ndarray, lo: np.ndarray, hi: np.ndarray, level: float
             ) -> tuple[np.ndarray, np.ndarray]:
    """Sandwich interval of a vector estimate ``x``: Jacobian of the residual by central
    differences of 2% of each parameter's range (one-sided where a side is out of bounds or
    unstable), Gauss-Newton Hessian ``H = 2 J^T J``, per-block scores ``2 J_b^T r_b``; half
    widths ``t sqrt(diag(H^-1 V H^-1))``, clipped to the bounds."""
    r0 = obj.residual(x)
    cols = []
    for i in range(len(x)):
        h = 0.02 * (hi[i] - lo[i])
        e = np.zeros_like(x)
        e[i] = h
        pts = [v for v in (x + e, x - e) if lo[i] <= v[i] <= hi[i]]
        rs = []
        for v in pts:
            u0 = obj.unstable
            r = obj.residual(v)
            if obj.unstable == u0:
                rs.append((v[i] - x[i], r))
        if len(rs) == 2:
            cols.append((rs[0][1] - rs[1][1]) / (rs[0][0] - rs[1][0]))
        elif rs:
            cols.append((rs[0][1] - r0) / rs[0][0])
        else:
            cols.append(np.zeros_like(r0))
    J = np.stack(cols, -1)  # [M, nv, p]
    H = 2 * np.einsum("mvi,mvj->ij", J, J)
    G = np.zeros((obj.nb, len(x)))
    np.add.at(G, obj.ids, 2 * np.einsum("mv,mvi->mi", r0, J))
    Hi = np.linalg.pinv(H)
    cov = Hi @ _score_var(G, obj.nxt) @ Hi
    half = _quantile(level, obj.nb) * np.sqrt(np.maximum(np.diag(cov), 0.0))
    flat = np.diag(H) <= 1e-12 * max(float(np.abs(H).max()), 1e-300)
    half = np.where(flat, np.inf, half)
    return np.clip(x - half, lo, x), np.clip(x + half, x, hi)


class _Along:
    """The objective along component ``i`` of ``x`` (the others held at the estimate): what
    :func:`paired_interval` reads (``block_losses`` of a one-entry vector, ``nxt``)."""

    def __init__(self, obj: Objective, x: np.ndarray, i: int):
        self.obj, self.x, self.i, self.nxt = obj, x, i, obj.nxt

    def block_losses(self, v: np.ndarray) -> np.ndarray:
        p = self.x.copy()
        p[self.i] = float(np.asarray(v).ravel()[0])
        return self.obj.block_losses(p)


def vector_interval(obj: Objective, x: np.ndarray, lo: np.ndarray, hi: np.ndarray, level: float
                    ) -> tuple[np.ndarray, np.ndarray, dict]:
    """Interval of a vector estimate ``x`` (one effect's components, e.g. the centre of mass
    offset): the :func:`sandwich`, whose covariance sees how the components trade against each
    other, where the loss is quadratic near ``x``; along a component where it is not -- its
    curvature along that component at half the sandwich half width is more than :data:`KINK`
    times that at four or sixteen times the step, the rule of :func:`scalar_interval` -- the hull of the
    sandwich and :func:`paired_interval` along that component with the others at the estimate
    (no curvature needed: it holds where the loss is rough). ``info["rough"]``: which components.

    Why: on the Go1 the centre-of-mass offset's loss is rough at the scale the least squares stops
    at (noise-free logs of a planted 0.03 m gave 0.026-0.030), so the sandwich's curvature says
    little of where the estimate falls; over 30 noisy draws it covered the planted value in 7, 10
    and 20 of 30 (x, y, z) with half widths a sixth of the estimates' spread
    (``results/gap_coverage/go1``), where the pendulum's smooth loss gave 95-100%."""
    sl, sh = sandwich(obj, x, lo, hi, level)
    Lx = obj.block_losses(x)
    f = float(Lx.sum())
    rough, curv = [], []
    for i in range(len(x)):
        xi, lo_i, hi_i = float(x[i]), float(lo[i]), float(hi[i])
        h = float(np.clip((sh[i] - sl[i]) / 4, 1e-4 * (hi_i - lo_i), 0.05 * (hi_i - lo_i)))
        # the curvature along the component at the step and at SCALES times it: every node off
        # the estimate in one batched replay
        stencils = [_nodes(xi, k * h, lo_i, hi_i) for k in (1, *SCALES)]
        off = [v for t in stencils for v in t if v != xi]
        at = dict(zip(off, obj.block_losses_many([np.where(np.arange(len(x)) == i, v, x) for v in off]).sum(1)))
        H, *wide = [float(_lagrange(t, xi)[1] @ np.array([f if v == xi else at[v] for v in t])) for t in stencils]
        curv.append((H, *wide))
        if _rough(H, wide):
            rough.append(i)
            a, b = paired_interval(_Along(obj, x, i), xi, Lx, lo_i, hi_i, level, 4 * h)
            sl[i], sh[i] = min(sl[i], a), max(sh[i], b)
    return sl, sh, {"rough": rough, "curvature": curv}
