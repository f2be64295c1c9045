"""Fitting effect parameters to logged trajectories by one-step replay.

The objective is the k-step residual (multiple shooting): from every logged state, the simulator
with the candidate effect runs ``k`` control periods under the logged commands, and its velocity is
compared with the logged one. ``r = (qd_pred - qd_log) / (k ctrl_dt)`` is an acceleration error
(averaged over the horizon); a systematic gap grows with ``k`` while velocity noise does not, so
``k > 1`` lifts weak effects out of sensor noise (``k = 1`` is the plain one-step replay); each dof is divided by the spread of its logged velocity changes so that base and
joints weigh alike. Losses are kept per trajectory so that intervals can resample trajectories.

Optimisers, per the lessons the issue lists:

* integer parameters (delay) are searched on their whole grid, never locally;
* scalar parameters: a coarse grid over the bounds, then a bounded Brent search in the best cell
  (no derivatives, so steps across contact events do no harm);
* vectors and pairs: a box-constrained trust-region least squares (``scipy.optimize.least_squares``)
  in coordinates normalised to the bounds, with a 2%-of-range finite-difference step (large steps:
  tiny ones straddle contact events and give meaningless Jacobians);
* intervals come from resampling trajectories (a profile of per-trajectory losses on a grid for
  scalars, refits for vectors), not from Gauss-Newton covariances.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np
from scipy import optimize

from stride_jax.gap import effects, logs, sim
from stride_jax.sim.model import SimModel


class Data(NamedTuple):
    """Logged trajectories concatenated for batched replay.

    ``q [N, nq]``, ``qd [N, nv]``, ``cmd [N, nu]``; ``bounds [n + 1]`` trajectory starts;
    ``k`` control periods per replay; ``start [M]`` replayed samples (``start + k`` inside the
    trajectory), ``first [M]`` the first sample of their trajectory, ``target [M, nv]`` the logged
    velocity ``k`` periods later, ``traj [M]`` their trajectory; ``names`` of the trajectories.
    """

    q: np.ndarray
    qd: np.ndarray
    cmd: np.ndarray
    bounds: np.ndarray
    k: int
    start: np.ndarray
    first: np.ndarray
    target: np.ndarray
    traj: np.ndarray
    names: tuple[str, ...]

    @property
    def n(self) -> int:
        return len(self.names)


def make_data(trajs: list[logs.Trajectory], k: int = 1) -> Data:
    """Concatenates trajectories (each needs more than ``k`` samples)."""
    if not trajs:
        raise ValueError("no trajectories")
    short = [t.name for t in trajs if len(t.t) <= k]
    if short:
        raise ValueError(f"trajectories {short} have at most {k} samples; need more than k = {k}")
    lens = [len(t.t) for t in trajs]
    bounds = np.cumsum([0] + lens)
    start = np.concatenate([np.arange(a, b - k) for a, b in zip(bounds[:-1], bounds[1:])])
    first = np.concatenate([np.full(n - k, a) for a, n in zip(bounds[:-1], lens)])
    qd = np.concatenate([t.qd for t in trajs])
    return Data(q=np.concatenate([t.q for t in trajs]), qd=qd,
                cmd=np.concatenate([t.cmd for t in trajs]), bounds=bounds, k=k, start=start,
                first=first, target=qd[start + k],
                traj=np.concatenate([np.full(n - k, i) for i, n in enumerate(lens)]),
                names=tuple(t.name for t in trajs))


def subset(data: Data, idx) -> Data:
    """The trajectories ``idx`` of ``data``."""
    idx = list(idx)
    b = data.bounds
    trajs = [logs.Trajectory(data.names[i], np.zeros(b[i + 1] - b[i]), data.q[b[i]:b[i + 1]],
                             data.qd[b[i]:b[i + 1]], data.cmd[b[i]:b[i + 1]], None, None) for i in idx]
    return make_data(trajs, data.k)


def samples_before_next(data: Data) -> np.ndarray:
    """``[M]`` index into ``q``/``qd`` of each replayed sample."""
    return data.start


def residual(sm: SimModel, plan: effects.Plan, data: Data, scale: np.ndarray) -> np.ndarray:
    """``[M, nv]`` scaled ``k``-step residual (dimensionless): velocity error after ``k`` periods
    per second of replay, divided by ``scale [nv]``; diverged replays count as large."""
    _, qd = sim.k_step(sm, plan, data.q, data.qd, data.cmd, data.start, data.first, data.k)
    r = (qd - data.target) / (data.k * sm.robot.ctrl_dt * scale)
    return np.where(np.isfinite(r), np.clip(r, -1e3, 1e3), 1e3)


def gap(r: np.ndarray) -> float:
    """The gap of residuals ``r [M, nv]``: mean over samples of the squared scaled residual
    summed over dofs (what "gap explained" is a fraction of)."""
    return float((r ** 2).sum(1).mean()) if len(r) else 0.0


def per_traj(r: np.ndarray, data: Data) -> np.ndarray:
    """``[n]`` sum of squared residuals of each trajectory."""
    return np.bincount(data.traj, weights=(r ** 2).sum(1), minlength=data.n)


class Objective:
    """Per-trajectory loss of parameters ``p`` of ``effects`` (concatenated), on top of ``base``."""

    def __init__(self, sm: SimModel, data: Data, scale: np.ndarray, names: tuple[str, ...],
                 base: dict | None = None):
        self.sm, self.data, self.scale, self.names, self.base = sm, data, scale, names, dict(base or {})
        self.sizes = [effects.ALL[n].size for n in names]
        self.evals = 0

    def applied(self, p: np.ndarray) -> dict:
        out, i = dict(self.base), 0
        for n, k in zip(self.names, self.sizes):
            out[n] = np.asarray(p[i:i + k], np.float64)
            i += k
        return out

    def residual(self, p: np.ndarray) -> np.ndarray:
        self.evals += 1
        return residual(self.sm, effects.build(self.sm, self.applied(p)), self.data, self.scale)

    def losses(self, p: np.ndarray) -> np.ndarray:
        return per_traj(self.residual(p), self.data)


class Fit(NamedTuple):
    """A fitted hypothesis: effect names, parameters (name -> vector), training loss and the
    bootstrap spread of the parameters (``lo``/``hi``: 5th/95th percentiles, name -> vector)."""

    names: tuple[str, ...]
    params: dict
    train_loss: float
    lo: dict
    hi: dict
    evals: int


@dataclasses.dataclass(frozen=True)
class FitConfig:
    """Optimiser settings.

    Attributes:
      grid: coarse grid points per scalar parameter.
      profile: points of the local profile used for scalar intervals.
      bootstrap: trajectory resamples for intervals.
      refits: bootstrap refits for vector parameters (0: no interval).
      max_nfev: least-squares evaluations per parameter.
      seed: of the resampling.
    """

    grid: int = 9
    profile: int = 13
    bootstrap: int = 200
    refits: int = 4
    max_nfev: int = 12
    seed: int = 0


def _bounds(sm: SimModel, names) -> tuple[np.ndarray, np.ndarray]:
    lo, hi = zip(*(effects.ALL[n].bounds(sm) for n in names))
    return np.concatenate(lo), np.concatenate(hi)


def _split(names, vec) -> dict:
    out, i = {}, 0
    for n in names:
        k = effects.ALL[n].size
        out[n] = np.asarray(vec[i:i + k], np.float64)
        i += k
    return out


def _boot_argmin(xs: np.ndarray, L: np.ndarray, rng, B: int) -> np.ndarray:
    """Bootstrap over trajectories of the minimiser of ``sum_i L[x, i]`` on the grid ``xs``,
    refined by a parabola through the best point and its neighbours. ``L [X, n]``."""
    n = L.shape[1]
    w = rng.multinomial(n, np.full(n, 1 / n), size=B)  # [B, n] resample counts
    tot = w @ L.T  # [B, X]
    out = np.empty(B)
    for b in range(B):
        k = int(np.argmin(tot[b]))
        if 0 < k < len(xs) - 1:
            y0, y1, y2 = tot[b, k - 1:k + 2]
            den = y0 - 2 * y1 + y2
            step = 0.5 * (y0 - y2) / den if den > 0 else 0.0
            out[b] = xs[k] + np.clip(step, -1, 1) * (xs[k + 1] - xs[k - 1]) / 2
        else:
            out[b] = xs[k]
    return out


def fit_scalar(obj: Objective, cfg: FitConfig, integer: bool, lo: float, hi: float
               ) -> tuple[float, float, float, float]:
    """Minimises a one-parameter objective; returns ``(x, loss, x_lo, x_hi)``."""
    rng = np.random.default_rng(cfg.seed)
    if integer:
        xs = np.arange(int(lo), int(hi) + 1, dtype=float)
        L = np.stack([obj.losses(np.array([x])) for x in xs])
        boot = xs[np.argmin(rng.multinomial(L.shape[1], np.full(L.shape[1], 1 / L.shape[1]),
                                            size=cfg.bootstrap) @ L.T, axis=1)]
        k = int(np.argmin(L.sum(1)))
        return float(xs[k]), float(L[k].sum()), *np.percentile(boot, [5, 95]).tolist()
    nom = float(effects.ALL[obj.names[-1]].nominal[0])
    xs = np.unique(np.concatenate([np.linspace(lo, hi, cfg.grid), [nom]]))
    L = np.stack([obj.losses(np.array([x])) for x in xs])
    k = int(np.argmin(L.sum(1)))
    a, b = xs[max(k - 1, 0)], xs[min(k + 1, len(xs) - 1)]
    res = optimize.minimize_scalar(lambda x: obj.losses(np.array([x])).sum(), bounds=(a, b),
                                   method="bounded", options={"xatol": 1e-4 * (hi - lo), "maxiter": 25})
    x, f = (float(res.x), float(res.fun)) if res.fun <= L[k].sum() else (float(xs[k]), float(L[k].sum()))
    if cfg.bootstrap and cfg.profile:
        half = max((b - a) / 2, 1e-3 * (hi - lo))
        px = np.clip(np.linspace(x - half, x + half, cfg.profile), lo, hi)
        px = np.unique(px)
        PL = np.stack([obj.losses(np.array([v])) for v in px])
        boot = _boot_argmin(px, PL, rng, cfg.bootstrap)
        x_lo, x_hi = np.percentile(boot, [5, 95])
    else:
        x_lo = x_hi = x
    return x, f, float(x_lo), float(x_hi)


def fit_vector(obj: Objective, cfg: FitConfig, x0: np.ndarray, lo: np.ndarray, hi: np.ndarray
               ) -> tuple[np.ndarray, float]:
    """Box-constrained least squares in coordinates normalised to the bounds."""
    span = hi - lo
    z0 = np.clip((x0 - lo) / span, 0, 1)
    fun = lambda z: obj.residual(lo + z * span).ravel()
    res = optimize.least_squares(fun, z0, bounds=(0, 1), diff_step=0.02, method="trf",
                                 max_nfev=cfg.max_nfev * len(x0), x_scale=1.0)
    x = lo + res.x * span
    f0 = obj.losses(x0).sum()
    f = 2 * res.cost
    return (x, f) if f <= f0 else (x0, f0)


def fit(sm: SimModel, data: Data, scale: np.ndarray, names: tuple[str, ...], cfg: FitConfig,
        start: dict | None = None) -> Fit:
    """Fits the effects ``names`` jointly on ``data`` (start from ``start`` where given)."""
    names = tuple(names)
    ints = [n for n in names if effects.ALL[n].integer]
    conts = [n for n in names if not effects.ALL[n].integer]
    start = dict(start or {})
    rng = np.random.default_rng(cfg.seed)
    evals = 0
    if len(names) == 1:
        (name,) = names
        e = effects.ALL[name]
        lo, hi = _bounds(sm, names)
        obj = Objective(sm, data, scale, names)
        if e.size == 1:
            x, f, xl, xh = fit_scalar(obj, cfg, e.integer, lo[0], hi[0])
            return Fit(names, {name: np.array([x])}, f, {name: np.array([xl])}, {name: np.array([xh])},
                       obj.evals)
        x0 = np.asarray(start.get(name, e.nominal), float)
        x, f = fit_vector(obj, cfg, x0, lo, hi)
        los, his = _refit_interval(sm, data, scale, names, cfg, x, lo, hi, rng)
        return Fit(names, {name: x}, f, _split(names, los), _split(names, his), obj.evals)
    if ints:  # grid over the integer effect near its single estimate, fit the rest at each value
        (iname,) = ints[:1]
        hi_i = int(effects.ALL[iname].bounds(sm)[1][0])
        centre = int(round(float(np.asarray(start.get(iname, [0]))[0])))
        best = None
        for d in sorted({min(max(centre + k, 0), hi_i) for k in (-1, 0, 1)}):
            obj = Objective(sm, data, scale, tuple(conts), base={iname: np.array([float(d)])})
            lo, hi = _bounds(sm, conts)
            x0 = np.concatenate([np.asarray(start.get(n, effects.ALL[n].nominal), float) for n in conts])
            x, f = fit_vector(obj, cfg, x0, lo, hi)
            evals += obj.evals
            if best is None or f < best[1]:
                best = (d, f, x)
        d, f, x = best
        params = {iname: np.array([float(d)])} | _split(conts, x)
        return Fit(names, params, f, params, params, evals)
    lo, hi = _bounds(sm, names)
    x0 = np.concatenate([np.asarray(start.get(n, effects.ALL[n].nominal), float) for n in names])
    obj = Objective(sm, data, scale, names)
    x, f = fit_vector(obj, cfg, x0, lo, hi)
    los, his = _refit_interval(sm, data, scale, names, cfg, x, lo, hi, rng)
    return Fit(names, _split(names, x), f, _split(names, los), _split(names, his), obj.evals)


def _refit_interval(sm, data, scale, names, cfg, x, lo, hi, rng):
    if not cfg.refits or data.n < 2:
        return x, x
    xs = []
    for _ in range(cfg.refits):
        idx = rng.integers(0, data.n, data.n)
        obj = Objective(sm, subset(data, idx), scale, names)
        xs.append(fit_vector(obj, dataclasses.replace(cfg, max_nfev=max(cfg.max_nfev // 2, 3)), x, lo, hi)[0])
    xs = np.stack(xs)
    return np.percentile(xs, 5, axis=0), np.percentile(xs, 95, axis=0)
