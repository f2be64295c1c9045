"""The cheap screen before the full fits: one batched replay of every candidate at a probe value,
a linearised cross-validated score for each, a check of the best at their linear estimate, and the
sensitivity columns that say which effects the logs cannot tell apart.

Why: a full fit of one effect on the Go1 costs 15-40 replays of every logged state (a grid, a
line search, the profile interval), and the library with its finer variants (per joint group,
encoder offsets, link groups, base wrench: :mod:`stride_jax.gap.finer`) holds about a hundred
candidates. The screen spends one replay per parameter (a joint effect on a side or end of a quadruped adds
up its limbs' columns instead: :func:`stride_jax.gap.finer.unions`), all in one threaded
``mujoco.rollout`` batch (:mod:`stride_jax.gap.replay`), on every ``stride``-th replay window:

1. **Sensitivity columns**: for each parameter ``i`` of each candidate the secant
   ``J_i = (r(p0 + h_i e_i) - r(p0)) / h_i`` of the scaled ``k``-step residual ``[M, nv]``, with the
   probe step ``h_i`` a fraction (``probe``) of the way from the nominal value to the farther bound
   (a secant, not a derivative: a torque limit or a dead band does nothing for small steps).
2. **Linearised cross-validated score**: the residual model ``r(p) ~ r0 + J (p - p0)`` is fitted by
   bounded least squares on all training trajectories but one and scored on the one left out, in
   turn (:func:`folds`): the fraction of the gap it removes out of sample, like the full
   diagnosis's held-out "explained" but to first order. Cross-validation on the training windows
   replaces the held-out columns the screen used to replay (a third of its replays) and scores on
   all of its windows rather than on the held-out third.
3. **One-step check**: the ``check`` best (at most two members of one effect) are replayed once at
   their linear estimate on the held-out windows (one batch; their training windows were replayed
   too until session 30, for a record nothing read: 8 of the Go1 screen's 70 s);
   their actual held-out gap there ranks them, and the best member (all joints or one group) of
   each of the ``shortlist`` best effects goes to the full fits, plus the leading effect's
   all-joints and best group variant (the rivals of the finer choice; should another finer variant
   come out best, :func:`~stride_jax.gap.attribute.which` fits its all-joints effect too; other
   groups of the same effect come in as pairs).
4. **Pairs**: a second effect on top of the best single is proposed by the joint linear fit of
   both columns (``pairs`` of them), which sees an effect masked by the first; a pair whose linear
   fit does not remove ``pair_min`` of what the single's leaves is not fitted.
5. **Collinearity**: two scalar candidates whose training columns have ``|cos| >= collinear`` move
   the replays the same way: to first order the logs cannot tell them apart (a position servo's gain
   and the motor constant when nothing saturates, joint and servo damping without measured torque).
"""

from __future__ import annotations

import collections
import dataclasses
import time
from typing import Any

import numpy as np
from scipy import optimize

from stride_jax.gap import effects, finer, fit, granularity, progress, replay
from stride_jax.sim.model import SimModel


@dataclasses.dataclass(frozen=True)
class ScreenConfig:
    """The screen before the full fits.

    Attributes:
      shortlist: singles fitted in full after the screen; 0 skips the screen and fits every
        candidate (the full path, as slow as the library is long).
      finer: candidates include the finer effects (per joint group, encoder offsets, link groups,
        base wrench, servo damping); off: the plain library only.
      stride: the screen replays from every ``stride``-th sample (0: every ``steps``-th, so that
        its ``k``-step windows tile the logs).
      probe: secant step as a fraction of the way from the nominal value to the farther bound.
      check: candidates replayed at their linear estimate (the one-step check; at most
        :data:`CHECK_PER_EFFECT` of one effect and its finer variants).
      pairs: pairs proposed for full fits on top of the best single (the full path's conditional
        grid screen is not run).
      collinear: ``|cos|`` of two candidates' sensitivity columns above which they are reported
        as one indistinguishable set.
      fit_stride: the full fits replay from every ``fit_stride``-th sample of the training logs
        (their ``steps``-period windows overlap; 1: every sample). Held-out scores use every one.
      windows: the screen's stride grows where it would leave more than this many training
        windows (0: no cap); the held-out windows of its check take the same stride.
      fit_windows: the full fits' stride grows where ``fit_stride`` would leave more than this
        many training windows (0: no cap); so does the cross-fit's on the held-out split. Logs
        of a few minutes are thinned, shorter ones are fitted on every window
        (:func:`fit_stride_of`).
      finer_margin: a finer variant (``damping@calf``) is preferred to its all-joints effect only
        if it removes at least this fraction of what the all-joints effect leaves of the held-out
        gap above the noise floor, and the paired bootstrap puts its gain above zero at level
        ``alpha`` (:mod:`stride_jax.gap.granularity`).
    """

    shortlist: int = 4
    finer: bool = True
    stride: int = 0
    probe: float = 0.25
    check: int = 12
    pairs: int = 2
    collinear: float = 0.98
    fit_stride: int = 1
    finer_margin: float = 0.1
    windows: int = 400
    fit_windows: int = 1000

    def __post_init__(self):
        if self.fit_stride < 1:
            raise ValueError(f"screen.fit_stride must be >= 1, got {self.fit_stride}")
        for f in ("shortlist", "stride", "check", "pairs", "windows", "fit_windows"):
            if getattr(self, f) < 0:
                raise ValueError(f"screen.{f} must be >= 0, got {getattr(self, f)}")
        if not 0 < self.probe <= 1:
            raise ValueError(f"screen.probe must be in (0, 1], got {self.probe}")
        if not 0 < self.collinear <= 1:
            raise ValueError(f"screen.collinear must be in (0, 1], got {self.collinear}")
        if self.finer_margin < 0:
            raise ValueError(f"screen.finer_margin must be >= 0, got {self.finer_margin}")


CHECK_PER_EFFECT = 2
"""The one-step check replays at most this many members of one effect (``damping`` and its finer
variants): on the independent Go1 benchmark's noisy torque-limit case, the finer variants of
four effects filled the twelve places, and the torque limit, whose secant underrates it (a limit
acts only once reached), was never replayed at its estimate (named: torque_scale, 59% against the
limit's 90%)."""


def candidate_names(sm: SimModel, cfg: ScreenConfig) -> list[str]:
    """The library effects that apply to ``sm``, then (with ``cfg.finer``) the finer ones."""
    out = [e.name for e in effects.candidates(sm)]
    return out + (finer.candidates(sm) if cfg.finer else [])


def fit_stride_of(cfg: ScreenConfig, n: int) -> int:
    """The full fits' stride over ``n`` training windows: ``cfg.fit_stride``, larger where that
    leaves more than ``cfg.fit_windows``. Measured on 12 x 8 s Go1 logs (3160 training windows,
    shipped model: ~6 s per evaluation of all of them), the fits were 70% of the diagnosis."""
    return fit.capped_stride(cfg.fit_stride, n, cfg.fit_windows)


def rows_every(data: fit.Data, stride: int) -> np.ndarray:
    """Replays of ``data`` starting every ``stride`` samples of each trajectory."""
    local = data.start - data.bounds[data.traj]
    return np.flatnonzero(local % max(stride, 1) == 0)


def _probe(sm: SimModel, name: str, frac: float) -> np.ndarray:
    """``[size]`` secant steps: ``frac`` of the way from nominal to the farther bound (at least
    one step for an integer effect)."""
    e = effects.ALL[name]
    lo, hi = e.bounds(sm)
    nom = np.asarray(e.nominal, float)
    h = np.where(hi - nom >= nom - lo, frac * (hi - nom), -frac * (nom - lo))
    if e.integer:
        h = np.sign(h) * np.maximum(np.round(np.abs(h)), 1.0)
    return h


@dataclasses.dataclass
class Columns:
    """Sensitivity columns on training windows: ``names`` of the candidates, ``param`` ``[C]``
    (candidate, parameter) of each column, ``step [C]``, the residual at the base ``r0_tr [M, nv]``,
    the columns ``J_tr [C, M, nv]`` (per unit of the parameter) and ``fold [M]``, the
    cross-validation fold of each window (:func:`folds`)."""

    names: list[str]
    param: list[tuple[str, int]]
    step: np.ndarray
    r0_tr: np.ndarray
    J_tr: np.ndarray
    fold: np.ndarray

    def cols(self, name: str) -> list[int]:
        return [c for c, (n, _) in enumerate(self.param) if n == name]


def folds(data: fit.Data, rows: np.ndarray, n_min: int = 3) -> np.ndarray:
    """``[len(rows)]`` cross-validation fold of each replay ``rows`` of ``data``: its trajectory
    where there are at least ``n_min`` (whole trajectories, like the held-out split), else the
    quarter of its trajectory it falls in (contiguous stretches)."""
    traj = data.traj[rows]
    if len(np.unique(traj)) >= n_min:
        return np.unique(traj, return_inverse=True)[1].ravel()
    b = data.bounds
    local = (data.start[rows] - b[traj]) / np.maximum(b[traj + 1] - b[traj], 1)
    return (traj * 4 + np.minimum((local * 4).astype(int), 3)).astype(int)


def columns(sm: SimModel, names: list[str], train: fit.Data, scale: np.ndarray, cfg: ScreenConfig,
            rows_tr: np.ndarray, base: dict | None = None, show: bool = True) -> Columns:
    """Secant columns of every parameter of ``names`` on top of ``base`` (applied effects), on the
    replays ``rows_tr`` of ``train``: one batched replay. A joint effect on a union of limbs with
    the same probe step as its limbs' (:func:`stride_jax.gap.finer.unions`) gets the sum of their
    columns, without a replay of its own."""
    base = dict(base or {})
    steps = {n: _probe(sm, n, cfg.probe) for n in names}
    derived = {n: parts for n, parts in finer.unions(sm, names).items()
               if all(np.array_equal(steps[q], steps[n]) for q in parts)}
    plans, param, step, replayed = [effects.build(sm, base)], [], [], []
    for n in names:
        e = effects.ALL[n]
        p0 = np.asarray(base.get(n, e.nominal), float)
        for i in range(e.size):
            param.append((n, i))
            step.append(steps[n][i])
            if n in derived:
                continue
            p = p0.copy()
            p[i] += steps[n][i]
            plans.append(effects.build(sm, base | {n: p}))
            replayed.append(len(param) - 1)
    R = []
    per = max(1, replay.CHUNK // max(len(rows_tr), 1))
    with progress.bar(len(plans), "screen: replay every candidate at a probe value", show) as bar:
        for c0 in range(0, len(plans), per):
            R.append(replay.residuals(sm, plans[c0:c0 + per], train, scale, rows_tr))
            bar.update(len(plans[c0:c0 + per]))
    R = np.concatenate(R)
    step = np.asarray(step, float)
    J = np.empty((len(param),) + R.shape[1:])
    J[replayed] = (R[1:] - R[0]) / step[replayed, None, None]
    at = {pr: c for c, pr in enumerate(param)}
    for n, parts in derived.items():
        J[at[(n, 0)]] = sum(J[at[(q, 0)]] for q in parts)
    return Columns(list(names), param, step, R[0], J, folds(train, rows_tr))


def _solve(A: np.ndarray, b: np.ndarray, dlo: np.ndarray, dhi: np.ndarray) -> np.ndarray:
    """Bounded least squares ``min |A d - b|`` over ``dlo <= d <= dhi``."""
    if A.shape[1] == 1:
        a = float(A[:, 0] @ A[:, 0])
        return np.clip([float(A[:, 0] @ b) / a if a > 0 else 0.0], dlo, dhi)
    return optimize.lsq_linear(A, b, bounds=(np.minimum(dlo, -1e-12), np.maximum(dhi, 1e-12))).x


def linear_fit(C: Columns, sm: SimModel, names: tuple[str, ...], base: dict | None = None
               ) -> tuple[dict, float, float]:
    """Bounded least squares of the linear residual model of the effects ``names`` on the training
    columns; returns ``(params, train gap fraction left, cross-validated gap fraction left)``: the
    latter fits on all folds but one and scores the one left out, in turn (:func:`folds`), so a
    candidate with more parameters gains nothing from fitting noise, as on a held-out split."""
    base = dict(base or {})
    idx = [c for n in names for c in C.cols(n)]
    p0 = np.concatenate([np.asarray(base.get(n, effects.ALL[n].nominal), float) for n in names])
    lo, hi = fit._bounds(sm, names)
    ints = np.concatenate([np.full(effects.ALL[n].size, effects.ALL[n].integer) for n in names])
    J = C.J_tr[idx]  # [p, M, nv]

    def solve(rows):
        d = _solve(J[:, rows].reshape(len(idx), -1).T, -C.r0_tr[rows].ravel(), lo - p0, hi - p0)
        return np.where(ints, np.round(p0 + d) - p0, d)  # integer parameters take integer values

    def left(rows, d):
        return float(((C.r0_tr[rows] + np.tensordot(d, J[:, rows], 1)) ** 2).sum())

    everything = np.arange(len(C.r0_tr))
    d = solve(everything)
    total = max(float((C.r0_tr ** 2).sum()), 1e-300)
    cv = sum(left(C.fold == f, solve(C.fold != f)) for f in np.unique(C.fold))
    return fit._split(names, p0 + d), left(everything, d) / total, cv / total


def collinear_with(C: Columns, name: str, threshold: float) -> dict[str, float]:
    """Scalar candidates whose training column has ``|cos| >= threshold`` with ``name``'s."""
    (c,) = C.cols(name) if len(C.cols(name)) == 1 else (None,)
    if c is None:
        return {}
    X = C.J_tr.reshape(len(C.param), -1)
    nrm = np.linalg.norm(X, axis=1)
    if nrm[c] == 0:
        return {}
    out = {}
    for n in C.names:
        cols = C.cols(n)
        if n == name or len(cols) != 1 or nrm[cols[0]] == 0:
            continue
        cos = float(X[c] @ X[cols[0]] / (nrm[c] * nrm[cols[0]]))
        if abs(cos) >= threshold:
            out[n] = cos
    return out


def run(sm: SimModel, train: fit.Data, test: fit.Data, scale: np.ndarray, cfg: ScreenConfig,
        penalty: float, show: bool = True, log=print) -> dict[str, Any]:
    """The screen: columns, linear scores, the one-step check, the shortlist. Returns a JSON-able
    table plus ``_columns`` (for :func:`pairs` and :func:`collinear_with`)."""
    t0 = time.time()
    names = candidate_names(sm, cfg)
    stride = fit.capped_stride(cfg.stride or train.k, len(train.start), cfg.windows)
    rows_tr, rows_te = rows_every(train, stride), rows_every(test, stride)
    C = columns(sm, names, train, scale, cfg, rows_tr, show=show)
    table = []
    for n in names:
        params, l_tr, l_cv = linear_fit(C, sm, (n,))
        k = effects.ALL[n].size
        table.append({"effect": n, "params": {n: params[n].round(6).tolist()}, "linear_train": 1 - l_tr,
                      "linear_cv": 1 - l_cv, "score": 1 - l_cv - penalty * k, "_p": params})
    table.sort(key=lambda r: -r["score"])
    top, per = [], collections.Counter()  # the best, at most CHECK_PER_EFFECT of one effect's members
    for r in table:
        fam = finer.parent(r["effect"])
        if len(top) < cfg.check and per[fam] < CHECK_PER_EFFECT:
            top.append(r)
            per[fam] += 1
    plans = [effects.build(sm, r["_p"]) for r in top]
    with progress.bar(1, "screen: one-step check at the linear estimates", show) as bar:
        r0_te, *R_te = replay.residuals(sm, [effects.build(sm)] + plans, test, scale, rows_te)
        bar.update(1)
    g_te = float((r0_te ** 2).sum())
    for r, b in zip(top, R_te, strict=True):
        r["checked_heldout"] = 1 - float((b ** 2).sum()) / max(g_te, 1e-300)
        r["score"] = r["checked_heldout"] - penalty * effects.ALL[r["effect"]].size
    table.sort(key=lambda r: -r["score"])
    best_of: dict[str, str] = {}  # the best member of each effect (damping, damping@calf, ... count once)
    for r in table:
        if len(best_of) == cfg.shortlist:
            break
        best_of.setdefault(finer.parent(r["effect"]), r["effect"])
    short = list(best_of.values())
    if table:  # the leading effect's finer choice is made by full fits: its all-joints effect and
        lead = finer.parent(table[0]["effect"])  # its best group variant both go in
        fin = next((r["effect"] for r in table if finer.parent(r["effect"]) == lead and r["effect"] != lead), None)
        for n in (fin, granularity.coarse_of(sm, table[0]["effect"])):
            if n is not None and n not in short:
                short.insert(1, n)
    for r in table:
        del r["_p"]
    log(f"  screen: {len(names)} candidates ({len(C.param)} parameters) on {len(rows_tr)} + {len(rows_te)} "
        f"windows, {time.time() - t0:.1f} s; shortlist {', '.join(short)}")
    return {"candidates": len(names), "parameters": len(C.param), "windows": [int(len(rows_tr)), int(len(rows_te))],
            "stride": int(stride), "table": table, "shortlist": short, "seconds": time.time() - t0, "_columns": C}


def pairs(sm: SimModel, C: Columns, best: str, fitted: dict, n: int, min_gain: float = 0.0
          ) -> list[tuple[tuple[str, str], dict]]:
    """The ``n`` second effects whose joint linear fit with ``best`` removes most of the cross-validated
    gap: ``[((best, other), start params)]`` (start: the fitted single and the linear estimate).
    Pairs whose linear fit removes at least ``min_gain`` of what ``best``'s own linear fit leaves
    out of sample are proposed (the pair rule's ``pair_min``, to first order); where none does, the one
    partner that removes most is proposed all the same (if it removes anything): a confident
    single needs the data to rule out a material second effect (:func:`stride_jax.gap.admit.pair_tests`),
    and the linear screen, to first order and on noisy logs, can miss one that the full fit finds."""
    if n == 0 or best not in C.names:
        return []
    _, _, l_single = linear_fit(C, sm, (best,))
    scored = []
    for other in C.names:
        if other == best or other == finer.parent(best) or finer.parent(other) == best:
            continue  # an effect and its own finer variant: nested, not a second effect
        params, _, l_cv = linear_fit(C, sm, (best, other))
        if l_cv < l_single:
            scored.append((l_cv, other, params))
    scored.sort(key=lambda t: t[0])
    keep = [t for t in scored if l_single - t[0] >= min_gain * l_single][:n] or scored[:1]
    return [((best, o), {best: np.asarray(fitted[best], float), o: p[o]}) for _, o, p in keep]
