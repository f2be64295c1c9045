"""Fitting effect parameters to logged trajectories by one-step replay.

The objective is the k-step residual (multiple shooting): from every logged state, the simulator
with the candidate effect runs ``k`` control periods under the logged commands, and its velocity is
compared with the logged one. ``r = (qd_pred - qd_log) / (k ctrl_dt)`` is an acceleration error
(averaged over the horizon); a systematic gap grows with ``k`` while velocity noise does not, so
``k > 1`` lifts weak effects out of sensor noise (``k = 1`` is the plain one-step replay); each dof is divided by the spread of its logged velocity changes so that base and
joints weigh alike. Losses are kept per trajectory so that intervals can resample trajectories.

Optimisers, per the lessons the issue lists:

* integer parameters (delay) are searched on their whole grid, never locally;
* scalar parameters: a coarse grid over the bounds, then successive parabolic interpolation in
  the best cell (:func:`line_search`: no derivatives, so steps across contact events do no harm)
  until a step would move the estimate by less than a quarter of its standard error
  (:func:`line_tol`);
* vectors and pairs: a box-constrained trust-region least squares (``scipy.optimize.least_squares``,
  stopped at a 0.01% step gain, :data:`FTOL`, or a step of ~0.1% of the ranges, :data:`XTOL`) in
  coordinates normalised to the bounds, with a 2%-of-range finite-difference step (large steps:
  tiny ones straddle contact events and give meaningless Jacobians);
* intervals (level ``FitConfig.level``, 90%) are calibrated by the spread of the loss's gradient
  over blocks of ``FitConfig.block`` control steps (a sandwich: the residuals are neither white nor
  of known variance; :func:`_score_var` says how neighbouring blocks are handled): scalars by the profile of the training loss, ``{x : L(x) - L(x^) <= c}`` with
  ``c = t^2 V / (2 H)`` (``V``: Newey-West variance of the per-block gradients, ``H``: curvature of
  ``L``, ``t``: Student quantile), found by bracketing and root finding; an integer (delay) by the
  hull of the values that a paired per-block test does not find worse than the estimate; vectors
  and pairs by the sandwich covariance ``H^-1 V H^-1`` of the Gauss-Newton Hessian ``H``, a
  vector also by the paired test along each component (the hull of both). Every
  interval is clipped to the bounds and contains its estimate; an estimate on a bound that is not
  its nominal value is flagged (the truth may lie beyond it).

A parameter value that makes MuJoCo diverge (NaN/Inf accelerations: MuJoCo resets the world, which
:func:`stride_jax.gap.sim.step` detects and turns into NaN) scores 1e3 per dof and replay, so the
optimisers stay away from it; :attr:`Objective.unstable` counts such evaluations.
"""

from __future__ import annotations

import collections
import dataclasses
from typing import NamedTuple

import numpy as np
from scipy import optimize

from stride_jax.gap import effects, logs, replay, sim
from stride_jax.gap.intervals import (_at_bound, _lagrange, _score_var, integer_set, sandwich, scalar_interval,
                                      vector_interval)
from stride_jax.sim.model import SimModel


class Data(NamedTuple):
    """Logged trajectories concatenated for batched replay.

    ``q [N, nq]``, ``qd [N, nv]``, ``cmd [N, nu]``; ``bounds [n + 1]`` trajectory starts;
    ``k`` control periods per replay; ``start [M]`` replayed samples (``start + k`` inside the
    trajectory), ``first [M]`` the first sample of their trajectory, ``target [M, nv]`` the logged
    velocity ``k`` periods later, ``traj [M]`` their trajectory; ``names`` of the trajectories;
    ``noise_floor``: the gap the logged velocities' noise adds to these replays when it is known
    (:func:`stride_jax.gap.regions.noise_floor_of`; None: read off the residuals).
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
    noise_floor: float | None = None

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


def thin(data: Data, stride: int) -> Data:
    """``data`` with the replays that start every ``stride``-th sample of each trajectory (the
    ``k``-step windows of neighbouring samples overlap by ``k - 1`` periods)."""
    if stride <= 1:
        return data
    keep = np.flatnonzero((data.start - data.bounds[data.traj]) % stride == 0)
    return data._replace(start=data.start[keep], first=data.first[keep], target=data.target[keep],
                         traj=data.traj[keep])


def capped_stride(stride: int, n: int, cap: int) -> int:
    """``stride``, or the smallest larger one that leaves at most ``cap`` (0: no cap) of ``n``
    replays: long logs cost what ``cap`` replays cost (neighbouring windows overlap)."""
    return max(stride, -(-n // cap) if cap else 1)


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


def block_ids(data: Data, length: int) -> tuple[np.ndarray, int, np.ndarray]:
    """Blocks of ``length`` consecutive control steps within each trajectory: ``ids [M]`` the block
    of each replayed sample, the number of blocks ``nb``, and ``nxt [nb]`` the next block of the
    same trajectory (-1 for a trajectory's last)."""
    local = data.start - data.bounds[data.traj]
    key = data.traj.astype(np.int64) * 10 ** 7 + local // max(int(length), 1)
    uniq, ids = np.unique(key, return_inverse=True)
    traj = uniq // 10 ** 7
    nxt = np.where(np.append(traj[1:] == traj[:-1], False), np.arange(1, len(uniq) + 1), -1)
    return ids.ravel(), len(uniq), nxt


class _Recent(collections.OrderedDict):
    """A dict that keeps its ``size`` most recently written entries (an objective's own cache: a
    vector fit asks for a few hundred residuals, and only recent ones are asked for again)."""

    def __init__(self, size: int):
        super().__init__()
        self.size = size

    def __setitem__(self, key, value):
        super().__setitem__(key, value)
        self.move_to_end(key)
        while len(self) > self.size:
            self.popitem(last=False)

    def update(self, other=(), **kw):
        for key, value in dict(other, **kw).items():
            self[key] = value


class Objective:
    """Per-trajectory (and per-block) loss of parameters ``p`` of ``effects`` (concatenated), on
    top of ``base``. ``evals`` counts evaluations, ``unstable`` those where a replay diverged.
    ``mask [M, nv]`` (0/1, optional) keeps only some entries of the residual: a fit on the samples
    of each joint where it moves slowly, say (:mod:`stride_jax.gap.form`). ``cache`` (a dict)
    keeps the unmasked residual of every parameter vector evaluated, so that no vector is replayed
    twice (the least squares' start and end, an interval's centre); objectives that share one and
    differ only in their mask replay each vector once (their grids coincide). Without one, each
    objective keeps its 64 most recent."""

    def __init__(self, sm: SimModel, data: Data, scale: np.ndarray, names: tuple[str, ...],
                 base: dict | None = None, block: int = 10, mask: np.ndarray | None = None,
                 cache: dict | None = None):
        self.sm, self.data, self.scale, self.names, self.base = sm, data, scale, names, dict(base or {})
        if mask is not None and np.shape(mask) != (len(data.start), sm.mj.nv):
            raise ValueError(f"mask has shape {np.shape(mask)}, needs (replayed samples, nv) = "
                             f"({len(data.start)}, {sm.mj.nv})")
        self.mask = None if mask is None else np.asarray(mask, np.float64)
        self.cache = _Recent(64) if cache is None else cache
        self.sizes = [effects.ALL[n].size for n in names]
        self.evals = 0
        self.unstable = 0
        self.ids, self.nb, self.nxt = block_ids(data, max(block, 4 * data.k))

    def applied(self, p: np.ndarray) -> dict:
        out, i = dict(self.base), 0
        for n, k in zip(self.names, self.sizes):
            out[n] = np.asarray(p[i:i + k], np.float64)
            i += k
        return out

    def _key(self, p) -> tuple:
        base = tuple(sorted((k, np.asarray(v, np.float64).tobytes()) for k, v in self.base.items()))
        return self.names, base, np.asarray(p, np.float64).tobytes()

    def residual(self, p: np.ndarray) -> np.ndarray:
        self.evals += 1
        r = None if self.cache is None else self.cache.get(self._key(p))
        if r is None:
            before = sim.unstable()["diverged"]
            r = residual(self.sm, effects.build(self.sm, self.applied(p)), self.data, self.scale)
            self.unstable += int(sim.unstable()["diverged"] > before)
            if self.cache is not None:
                self.cache[self._key(p)] = r
        return r if self.mask is None else r * self.mask

    def losses(self, p: np.ndarray) -> np.ndarray:
        return per_traj(self.residual(p), self.data)

    def block_losses(self, p: np.ndarray) -> np.ndarray:
        """``[nb]`` sum of squared residuals of each block."""
        return np.bincount(self.ids, weights=(self.residual(p) ** 2).sum(1), minlength=self.nb)

    def residual_many(self, ps) -> np.ndarray:
        """``[P, M, nv]`` :meth:`residual` of every parameter vector of ``ps``, in one batched replay
        (:mod:`stride_jax.gap.replay`; the same numbers as one at a time)."""
        ps = [np.atleast_1d(np.asarray(p, np.float64)) for p in ps]
        self.evals += len(ps)
        cached = {} if self.cache is None else {i: self.cache[k] for i, p in enumerate(ps)
                                                 if (k := self._key(p)) in self.cache}
        todo = [i for i in range(len(ps)) if i not in cached]
        if todo:
            before = sim.unstable()["diverged"]
            new = replay.residuals(self.sm, [effects.build(self.sm, self.applied(ps[i])) for i in todo],
                                   self.data, self.scale)
            self.unstable += int(sim.unstable()["diverged"] > before)
            cached.update(zip(todo, new))
            if self.cache is not None:
                self.cache.update({self._key(ps[i]): r for i, r in zip(todo, new)})
        R = np.stack([cached[i] for i in range(len(ps))])
        return R if self.mask is None else R * self.mask

    def losses_many(self, ps) -> np.ndarray:
        """``[P, n]`` :meth:`losses` of every parameter vector of ``ps`` (one batched replay)."""
        return np.stack([per_traj(r, self.data) for r in self.residual_many(ps)])

    def block_losses_many(self, ps) -> np.ndarray:
        """``[P, nb]`` :meth:`block_losses` of every parameter vector of ``ps`` (one batched replay)."""
        return np.stack([np.bincount(self.ids, weights=(r ** 2).sum(1), minlength=self.nb)
                         for r in self.residual_many(ps)])


class Fit(NamedTuple):
    """A fitted hypothesis: effect names, parameters (name -> vector), training loss, the
    parameters' confidence interval (``lo``/``hi``, name -> vector, level ``FitConfig.level``;
    equal to the estimate where none was computed), evaluations, ``at_bound`` (name -> bool
    vector: the estimate sits on a bound other than its nominal value) and ``unstable``
    (evaluations in which a replay diverged); ``grid_only``: a scalar left at its best grid node
    (:func:`fit`'s ``grid_only_above``); ``integer_fits``: for a hypothesis with an integer effect
    (a delay) beside continuous ones, the fit at each integer value tried (value -> (parameters,
    training loss)), the best of which is the estimate."""

    names: tuple[str, ...]
    params: dict
    train_loss: float
    lo: dict
    hi: dict
    evals: int
    at_bound: dict | None = None
    unstable: int = 0
    grid_only: bool = False
    integer_fits: dict | None = None


@dataclasses.dataclass(frozen=True)
class FitConfig:
    """Optimiser settings.

    Attributes:
      grid: coarse grid points per scalar parameter, beside its nominal value and the fit's hint
        (the screen's linear estimate): they find the best cell, the line search the minimum in
        it. 5, as the benchmarks' preset ``fast`` (9 until session 29: each point is a replay of
        every fitted window).
      profile: 0 skips the intervals (the estimate stands for its interval); any other value
        computes them (its size no longer matters: the profile is searched, not gridded).
      bootstrap: unused (intervals were bootstrap percentiles, which could miss the estimate;
        the held-out tests resample ``DiagnoseConfig.boot`` times); kept so that saved configs
        and benchmark rows still load.
      refits: unused, for the same reason.
      max_nfev: least-squares evaluations per parameter.
      seed: of the resampling.
      level: confidence level of the parameter intervals.
      block: control steps per block of the interval's variance estimate (at least 4 k is used:
        residuals of nearby steps are correlated; neighbouring blocks of a trajectory are taken
        as dependent, blocks further apart as independent).
    """

    grid: int = 5
    profile: int = 13
    bootstrap: int = 200
    refits: int = 4
    max_nfev: int = 12
    seed: int = 0
    level: float = 0.9
    block: int = 25


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


def fit_scalar(obj: Objective, cfg: FitConfig, integer: bool, lo: float, hi: float, hint: float | None = None,
               grid_only_above: float | None = None) -> tuple[float, float, float, float]:
    """Minimises a one-parameter objective; returns ``(x, loss, x_lo, x_hi)``: for an integer
    parameter the set at level ``cfg.level`` (``x`` itself when ``cfg.profile == 0``), for a
    continuous one ``x`` itself (its profile interval: :func:`with_interval`). ``hint``: a value
    the grid holds as well (the screen's linear estimate, a fit of the same effect on other
    data): near the minimum, it leaves the line search a narrow cell. ``grid_only_above``: a
    continuous parameter whose best grid loss is above it keeps its best grid node (no line
    search)."""
    if integer:
        xs = np.arange(int(lo), int(hi) + 1, dtype=float)
        B = obj.block_losses_many([[x] for x in xs])
        k = int(np.argmin(B.sum(1)))
        xl, xh = integer_set(B, xs, k, obj.nxt, cfg.level) if cfg.profile else (xs[k], xs[k])
        return float(xs[k]), float(B[k].sum()), xl, xh
    nom = float(effects.ALL[obj.names[-1]].nominal[0])
    extra = [nom] + ([] if hint is None else [float(np.clip(hint, lo, hi))])
    xs = np.unique(np.concatenate([np.linspace(lo, hi, cfg.grid), extra]))
    B = obj.block_losses_many([[x] for x in xs])  # [P, nb]
    L = B.sum(1)
    k = int(np.argmin(L))
    if grid_only_above is not None and L[k] > grid_only_above:
        return float(xs[k]), float(L[k]), float(xs[k]), float(xs[k])
    seen = dict(zip(xs.tolist(), L.tolist()))  # every point evaluated (their replays are cached)

    def loss(v: float) -> float:
        seen[float(v)] = float(obj.losses(np.array([v])).sum())
        return seen[float(v)]

    a, b = float(xs[max(k - 1, 0)]), float(xs[min(k + 1, len(xs) - 1)])
    tol = line_tol(obj, xs, B, k, hi - lo)
    for _ in range(REFINE):
        x, f, _ = line_search(loss, seen, a, b, tol)
        near = np.array(sorted(v for v in seen if a <= v <= b))
        i = int(np.searchsorted(near, x))
        if not 0 < i < len(near) - 1:
            break
        finer = line_tol(obj, near[i - 1:i + 2], obj.block_losses_many([[v] for v in near[i - 1:i + 2]]), 1,
                         hi - lo)
        if not finer < 0.5 * tol:
            break
        a, b, tol = float(near[i - 1]), float(near[i + 1]), finer
    return x, f, x, x


REFINE = 3
"""Line searches per scalar fit, each with the tolerance the last one's end implies (:func:`fit_scalar`).

The first search's tolerance (:func:`line_tol`) is read off the grid's best node and its
neighbours, which on a wide grid sit far from the minimum: there the per-block gradients vary
with the distance to it, not with the noise, and the tolerance comes out many standard errors
wide. Measured on noise-free pendulum logs (damping 0.3, 8 x 150 steps; bounds [-0.05, 5]): the
grid's tolerance was 0.0196 and the search stopped at 0.3042 (now 0.3001). On noisy logs this
changed nothing measurable: damping's +0.9 standard-error offset there (``results/gap_coverage/
long``, 82% coverage, rerun with this) has another cause: the joint velocity noise in the
replays' starts, errors in variables (session 55, ``results/gap_coverage/noise_terms``). The
tolerance read again at the end of a search, from the three points evaluated nearest its
estimate (cached replays: no new ones), is the
estimate's own; where it is under half the one used, the search goes on inside those points
with it."""


_GOLDEN = 0.3819660112501051


def line_search(f, known: dict[float, float], a: float, b: float, tol: float, maxiter: int = 25
                ) -> tuple[float, float, int]:
    """The minimum of ``f`` on ``[a, b]`` by safeguarded successive parabolic interpolation from
    the values ``known`` (``{x: f(x)}``, the grid's: its best inside ``[a, b]`` and that node's
    neighbours). Returns ``(x, f(x), evaluations)``: the best point evaluated.

    Each step evaluates the vertex of the parabola through the best point and its nearest
    evaluated neighbours on either side (a golden-section step into the larger side where that
    parabola is not convex or its vertex falls outside them; not the three best points, as
    Brent's method takes: on the rough loss of a legged robot's contacts, close points give
    parabolas of the roughness, not of the loss); the search stops when the next
    step would move the estimate by less than ``tol`` and a point within 1.5 ``tol`` of the
    estimate confirms the slope there (without one, the parabola may rest on far points: one is
    evaluated ``tol`` away first). For a loss nearly quadratic in the parameter (most effects over
    a grid cell) that is after two to four replays. Brent's bounded
    search (SciPy's ``fminbound``), which this replaced, stops only once its bracket has shrunk
    to ``tol``, and spent 7-11 replays per Go1 fit doing so. A best point on the edge of
    ``[a, b]`` (a bound of the parameter, where the grid's best node is its first or last) is
    tested first with one replay a golden step into the grid cell next to it (where the loss is
    lower there, the search goes on inside the cell), then with one ``tol`` inward: where the
    loss does not fall there either, the minimum is on the bound. The cell's probe comes first
    because a step of ``tol`` (at the edge, 1e-4 of the range) sees the contacts' roughness, not
    the slope: measured on the independent Go1 benchmark's noisy ground-friction case, the loss
    rose from 146.10 at the bound 0.2 to 146.13 at 0.2002 and the search stopped there, while
    the minimum (132.4, near 0.306) lay inside the cell [0.2, 0.65]."""
    pts = {float(x): float(v) for x, v in known.items()}
    n = 0
    cell_probed = False
    while n < maxiter:
        inside = sorted(x for x in pts if a <= x <= b)
        x = min(inside, key=pts.__getitem__)
        i = inside.index(x)
        left = inside[i - 1] if i > 0 else None
        right = inside[i + 1] if i + 1 < len(inside) else None
        if left is None or right is None:  # the best sits on a bound of the parameter (the grid's edge)
            inward = right if left is None else left
            if inward is None or abs(inward - x) <= tol:
                break
            if not cell_probed and abs(inward - x) > 2 * tol:  # is the minimum inside the cell?
                cell_probed = True
                v = x + _GOLDEN * (inward - x)
            else:
                v = x + tol if inward > x else x - tol  # does the loss fall inward from the bound at all?
                if v in pts:
                    break  # it does not: the minimum is on the bound, to within tol
        else:
            v = _vertex(x, left, right, pts)
            if v is None or not left < v < right:
                v = x + _GOLDEN * (right - x) if right - x >= x - left else x - _GOLDEN * (x - left)
            if abs(v - x) < tol:
                if min(x - left, right - x) <= 1.5 * tol:
                    break  # a neighbour within the tolerance: the slope at x is known, the step is small
                v = x + (tol if v >= x else -tol)  # else confirm with a point one tolerance away
        pts[float(v)] = float(f(v))
        n += 1
    x = min((y for y in pts if a <= y <= b), key=pts.__getitem__)
    return x, pts[x], n


def _vertex(x: float, y: float, z: float, pts: dict) -> float | None:
    """The vertex of the parabola through ``(x, y, z)`` and their values ``pts``; None where it is
    not convex."""
    d1, d2 = _lagrange(np.array([x, y, z]), x)
    f = np.array([pts[x], pts[y], pts[z]])
    slope, curv = float(d1 @ f), float(d2 @ f)
    return x - slope / curv if curv > 0 else None


LINE_SE = 0.25
"""The scalar line search's tolerance in standard errors of the estimate (:func:`line_tol`)."""


def line_tol(obj: Objective, xs: np.ndarray, B: np.ndarray, k: int, span: float) -> float:
    """The line search's tolerance on a scalar parameter: :data:`LINE_SE` (a quarter) of its
    standard error, as the grid ``xs`` (per-block losses ``B [P, nb]``, best node ``k``) sees it,
    within ``[1e-4, 1e-2]`` of the parameter's range ``span``.

    Searching an estimate closer than its own spread buys nothing (an optimiser's error of a
    quarter of the standard error, independent of the data's, adds at most 3% to the estimate's
    spread; a tenth, session 28's choice, 0.5%) and costs replays: on the rough loss of a legged
    robot's contacts each step of the line search near the minimum is a replay of every fitted
    window (the Go1's 12 x 8 s logs: a tenth took 6-7 steps per fit, a quarter 3-5,
    results/gap_speed.md). The standard error is the sandwich ``sqrt(V) / H`` of the parabola
    through the best node and its neighbours (``V``: variance of the per-block gradients, ``H``:
    curvature); a best node on the grid's edge, a flat or concave parabola keep the fine
    tolerance."""
    fine = 1e-4 * span
    if k == 0 or k == len(xs) - 1:
        return fine
    t = xs[k - 1:k + 2]
    d1, d2 = _lagrange(t, float(xs[k]))
    H = float(d2 @ B[k - 1:k + 2].sum(1))
    if not H > 0:
        return fine
    V = float(_score_var((d1 @ B[k - 1:k + 2])[:, None], obj.nxt)[0, 0])
    return float(np.clip(LINE_SE * np.sqrt(max(V, 0.0)) / H, fine, 1e-2 * span))


FTOL = 1e-4
"""Vectors and pairs: the least squares stops when a step lowers the training loss by less than
0.01% (SciPy's default, 1e-8, ran every pair fit to its evaluation budget on the rough loss of a
legged robot's contacts)."""

XTOL = 1e-3
"""Vectors and pairs: ... or when a trial step moves the parameters by less than ~0.1% of their
ranges (``norm(dz) < XTOL (XTOL + norm(z))`` in coordinates normalised to the bounds; SciPy's
default, 1e-8: where the loss is rough at that scale, the trust-region least squares shrinks its
radius fourfold per rejected trial, and the Go1's damping@calf + contact_softness pair replayed
the same point to four digits seven times, 7 s of a diagnosis). The estimates' own spread is
several times larger (that pair: 0.3% of the damping's range at one standard error)."""


def fit_vector(obj: Objective, cfg: FitConfig, x0: np.ndarray, lo: np.ndarray, hi: np.ndarray
               ) -> tuple[np.ndarray, float]:
    """Box-constrained least squares in coordinates normalised to the bounds."""
    span = hi - lo
    z0 = np.clip((x0 - lo) / span, 0, 1)
    fun = lambda z: obj.residual(lo + z * span).ravel()
    res = optimize.least_squares(fun, z0, bounds=(0, 1), diff_step=0.02, method="trf",
                                 max_nfev=cfg.max_nfev * len(x0), x_scale=1.0, ftol=FTOL, xtol=XTOL)
    x = lo + res.x * span
    x0 = lo + z0 * span  # the start as the least squares replayed it (cached)
    f0 = obj.losses(x0).sum()
    f = 2 * res.cost
    return (x, f) if f <= f0 else (x0, f0)


def _nominal(names) -> np.ndarray:
    return np.concatenate([np.asarray(effects.ALL[n].nominal, float) for n in names])


def fit(sm: SimModel, data: Data, scale: np.ndarray, names: tuple[str, ...], cfg: FitConfig,
        start: dict | None = None, interval: bool = True, mask: np.ndarray | None = None,
        cache: dict | None = None, grid_only_above: float | None = None) -> Fit:
    """Fits the effects ``names`` jointly on ``data`` (start from ``start`` where given; a
    continuous scalar's grid holds its start as well, :func:`fit_scalar`).

    ``interval=False`` leaves a single continuous effect's interval for later
    (:func:`with_interval`; the estimate stands for it meanwhile): the profile costs about a
    third of a scalar fit's replays, and a diagnosis reports intervals only for the hypotheses
    it names. ``mask [M, nv]``: fit on those entries of the residual only; ``cache``: replays
    shared with other fits on the same data and base (:class:`Objective`); ``grid_only_above``: a
    single continuous scalar whose best grid node's training loss is above it is left there
    (``Fit.grid_only``; :func:`stride_jax.gap.attribute.which` passes a multiple of its best
    single's loss: a line search that cannot change the ranking costs 2-7 replays)."""
    names = tuple(names)
    ints = [n for n in names if effects.ALL[n].integer]
    conts = [n for n in names if not effects.ALL[n].integer]
    start = dict(start or {})
    evals = unstable = 0
    lo, hi = _bounds(sm, names)
    bound_flags = lambda x: _split(names, _at_bound(x, lo, hi, _nominal(names)).astype(float))
    if len(names) == 1:
        (name,) = names
        e = effects.ALL[name]
        obj = Objective(sm, data, scale, names, block=cfg.block, mask=mask, cache=cache)
        if e.size == 1:
            hint = start.get(name)
            hint = None if hint is None else float(np.ravel(hint)[0])
            x, f, xl, xh = fit_scalar(obj, cfg, e.integer, lo[0], hi[0], hint, grid_only_above)
            grid_only = not e.integer and grid_only_above is not None and f > grid_only_above
            est = Fit(names, {name: np.array([x])}, f, {name: np.array([xl])}, {name: np.array([xh])},
                      obj.evals, _flags(bound_flags(np.array([x]))), obj.unstable, grid_only)
        else:
            x, f = fit_vector(obj, cfg, np.asarray(start.get(name, e.nominal), float), lo, hi)
            est = Fit(names, {name: x}, f, {name: x}, {name: x}, obj.evals, _flags(bound_flags(x)), obj.unstable)
        return with_interval(sm, data, scale, est, cfg, obj) if interval else est
    if ints:  # grid over the integer effect near its single estimate, fit the rest at each value
        (iname,) = ints[:1]
        hi_i = int(effects.ALL[iname].bounds(sm)[1][0])
        centre = int(round(float(np.asarray(start.get(iname, [0]))[0])))
        clo, chi = _bounds(sm, conts)
        tried = []
        for d in sorted({min(max(centre + k, 0), hi_i) for k in (-1, 0, 1)}):
            obj = Objective(sm, data, scale, tuple(conts), base={iname: np.array([float(d)])}, block=cfg.block,
                            mask=mask, cache=cache)
            x0 = np.concatenate([np.asarray(start.get(n, effects.ALL[n].nominal), float) for n in conts])
            x, f = fit_vector(obj, cfg, x0, clo, chi)
            tried.append((d, f, x, obj))
        k = int(np.argmin([t[1] for t in tried]))
        d, f, x, obj = tried[k]
        params = {iname: np.array([float(d)])} | _split(conts, x)
        los, his = dict(params), dict(params)
        if cfg.profile:
            # profile over the integer (the others refitted at each value), sandwich for the rest
            B = np.stack([t[3].block_losses(t[2]) for t in tried])
            il, ih = integer_set(B, np.array([float(t[0]) for t in tried]), k, obj.nxt, cfg.level)
            xl, xh = sandwich(obj, x, clo, chi, cfg.level)
            los = {iname: np.array([il])} | _split(conts, xl)
            his = {iname: np.array([ih])} | _split(conts, xh)
        evals = sum(t[3].evals for t in tried)
        unstable = sum(t[3].unstable for t in tried)
        vec = np.concatenate([params[n] for n in names])
        held = {float(t[0]): ({iname: np.array([float(t[0])])} | _split(conts, t[2]), float(t[1])) for t in tried}
        return Fit(names, params, f, los, his, evals, _flags(bound_flags(vec)), unstable, integer_fits=held)
    x0 = np.concatenate([np.asarray(start.get(n, effects.ALL[n].nominal), float) for n in names])
    obj = Objective(sm, data, scale, names, block=cfg.block, mask=mask, cache=cache)
    x, f = fit_vector(obj, cfg, x0, lo, hi)
    xl, xh = sandwich(obj, x, lo, hi, cfg.level) if cfg.profile else (x, x)
    return Fit(names, _split(names, x), f, _split(names, xl), _split(names, xh), obj.evals,
               _flags(bound_flags(x)), obj.unstable)


def with_interval(sm: SimModel, data: Data, scale: np.ndarray, f: Fit, cfg: FitConfig,
                  obj: Objective | None = None, mask: np.ndarray | None = None,
                  cache: dict | None = None) -> Fit:
    """``f`` (a single continuous effect fitted on ``data`` with ``interval=False``) with its
    interval at level ``cfg.level``: the profile for a scalar, :func:`vector_interval` for a vector; ``f``
    itself for anything else or where ``cfg.profile`` is 0. ``obj``: the fit's own objective
    (its evaluations are then counted once); else ``mask`` and ``cache`` as the fit had them."""
    if not cfg.profile or len(f.names) != 1 or effects.ALL[f.names[0]].integer:
        return f
    (name,) = f.names
    lo, hi = _bounds(sm, f.names)
    own = obj is not None  # the fit's objective has counted the fit's evaluations already
    obj = obj if own else Objective(sm, data, scale, f.names, block=cfg.block, mask=mask, cache=cache)
    x = np.asarray(f.params[name], float)
    if effects.ALL[name].size == 1:
        xl, xh, _ = scalar_interval(obj, float(x[0]), f.train_loss, lo[0], hi[0], cfg.level)
        xl, xh = np.array([xl], float), np.array([xh], float)
    else:
        xl, xh, _ = vector_interval(obj, x, lo, hi, cfg.level)
    return f._replace(lo={name: np.asarray(xl, float)}, hi={name: np.asarray(xh, float)},
                      evals=obj.evals + (0 if own else f.evals),
                      unstable=obj.unstable + (0 if own else f.unstable))


def _flags(d: dict) -> dict:
    return {k: np.asarray(v) > 0.5 for k, v in d.items()}
