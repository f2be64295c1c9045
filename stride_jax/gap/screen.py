"""The cheap screen before the full fits: one batched replay of every candidate at a probe value,
a linearised held-out score for each, a check of the best at their linear estimate, and the
sensitivity columns that say which effects the logs cannot tell apart.

Why: a full fit of one effect on the Go1 costs 30-40 replays of every logged state (a grid, a
Brent search, the profile interval), and the library with its finer variants (per joint group,
encoder offsets, link groups, base wrench: :mod:`stride_jax.gap.finer`) holds about a hundred
candidates. The screen spends one replay per parameter, all in one threaded ``mujoco.rollout``
batch (:mod:`stride_jax.gap.replay`), on every ``stride``-th replay window:

1. **Sensitivity columns**: for each parameter ``i`` of each candidate the secant
   ``J_i = (r(p0 + h_i e_i) - r(p0)) / h_i`` of the scaled ``k``-step residual ``[M, nv]``, with the
   probe step ``h_i`` a fraction (``probe``) of the way from the nominal value to the farther bound
   (a secant, not a derivative: a torque limit or a dead band does nothing for small steps).
2. **Linearised held-out score**: the residual model ``r(p) ~ r0 + J (p - p0)`` is fitted by bounded
   least squares on the training windows and scored on the held-out ones: the fraction of the
   held-out gap it removes, like the full diagnosis's "explained" but to first order.
3. **One-step check**: the ``check`` best are replayed once at their linear estimate (one batch);
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
      check: candidates replayed at their linear estimate (the one-step check).
      pairs: pairs proposed for full fits on top of the best single (the full path's conditional
        grid screen is not run).
      collinear: ``|cos|`` of two candidates' sensitivity columns above which they are reported
        as one indistinguishable set.
      fit_stride: the full fits replay from every ``fit_stride``-th sample of the training logs
        (their ``steps``-period windows overlap; 1: every sample). Held-out scores use every one.
      windows: the screen's stride grows where it would leave more than this many training
        windows (0: no cap); the held-out windows take the same stride.
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
    """Sensitivity columns: ``names`` of the candidates, ``param`` ``[C]`` (candidate, parameter)
    of each column, ``step [C]``, residuals at the base ``r0_tr [M1, nv]``, ``r0_te [M2, nv]`` and
    columns ``J_tr [C, M1, nv]``, ``J_te [C, M2, nv]`` (per unit of the parameter)."""

    names: list[str]
    param: list[tuple[str, int]]
    step: np.ndarray
    r0_tr: np.ndarray
    r0_te: np.ndarray
    J_tr: np.ndarray
    J_te: np.ndarray

    def cols(self, name: str) -> list[int]:
        return [c for c, (n, _) in enumerate(self.param) if n == name]


def columns(sm: SimModel, names: list[str], train: fit.Data, test: fit.Data, scale: np.ndarray,
            cfg: ScreenConfig, rows_tr: np.ndarray, rows_te: np.ndarray, base: dict | None = None,
            show: bool = True) -> Columns:
    """Secant columns of every parameter of ``names`` on top of ``base`` (applied effects), on the
    replays ``rows_tr`` of ``train`` and ``rows_te`` of ``test``: one batched replay."""
    base = dict(base or {})
    plans, param, step = [effects.build(sm, base)], [], []
    for n in names:
        e = effects.ALL[n]
        h = _probe(sm, n, cfg.probe)
        p0 = np.asarray(base.get(n, e.nominal), float)
        for i in range(e.size):
            p = p0.copy()
            p[i] += h[i]
            plans.append(effects.build(sm, base | {n: p}))
            param.append((n, i))
            step.append(h[i])
    R_tr, R_te = [], []
    per = max(1, replay.CHUNK // max(len(rows_tr) + len(rows_te), 1))
    with progress.bar(len(plans), "screen: replay every candidate at a probe value", show) as bar:
        for c0 in range(0, len(plans), per):
            R_tr.append(replay.residuals(sm, plans[c0:c0 + per], train, scale, rows_tr))
            R_te.append(replay.residuals(sm, plans[c0:c0 + per], test, scale, rows_te))
            bar.update(len(plans[c0:c0 + per]))
    R_tr, R_te = np.concatenate(R_tr), np.concatenate(R_te)
    step = np.asarray(step, float)
    return Columns(list(names), param, step, R_tr[0], R_te[0], (R_tr[1:] - R_tr[0]) / step[:, None, None],
                   (R_te[1:] - R_te[0]) / step[:, None, None])


def linear_fit(C: Columns, sm: SimModel, names: tuple[str, ...], base: dict | None = None
               ) -> tuple[dict, float, float]:
    """Bounded least squares of the linear residual model of the effects ``names`` on the training
    columns; returns ``(params, train gap fraction left, held-out gap fraction left)``."""
    base = dict(base or {})
    idx = [c for n in names for c in C.cols(n)]
    A = C.J_tr[idx].reshape(len(idx), -1).T  # [M1 nv, p]
    b = -C.r0_tr.ravel()
    p0 = np.concatenate([np.asarray(base.get(n, effects.ALL[n].nominal), float) for n in names])
    lo, hi = fit._bounds(sm, names)
    dlo, dhi = lo - p0, hi - p0
    if len(idx) == 1:
        a = float(A[:, 0] @ A[:, 0])
        d = np.clip([float(A[:, 0] @ b) / a if a > 0 else 0.0], dlo, dhi)
    else:
        d = optimize.lsq_linear(A, b, bounds=(np.minimum(dlo, -1e-12), np.maximum(dhi, 1e-12))).x
    if any(effects.ALL[n].integer for n in names):  # integer parameters take integer values
        k = 0
        for n in names:
            s = effects.ALL[n].size
            if effects.ALL[n].integer:
                d[k:k + s] = np.round(p0[k:k + s] + d[k:k + s]) - p0[k:k + s]
            k += s
    left = lambda r0, J: float(((r0 + np.tensordot(d, J[idx], 1)) ** 2).sum() / max((r0 ** 2).sum(), 1e-300))
    return fit._split(names, p0 + d), left(C.r0_tr, C.J_tr), left(C.r0_te, C.J_te)


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
    C = columns(sm, names, train, test, scale, cfg, rows_tr, rows_te, show=show)
    table = []
    for n in names:
        params, l_tr, l_te = linear_fit(C, sm, (n,))
        k = effects.ALL[n].size
        table.append({"effect": n, "params": {n: params[n].round(6).tolist()}, "linear_train": 1 - l_tr,
                      "linear_heldout": 1 - l_te, "score": 1 - l_te - penalty * k, "_p": params})
    table.sort(key=lambda r: -r["score"])
    top = table[:cfg.check]
    plans = [effects.build(sm, r["_p"]) for r in top]
    with progress.bar(2, "screen: one-step check at the linear estimates", show) as bar:
        R_tr = replay.residuals(sm, plans, train, scale, rows_tr)
        bar.update(1)
        R_te = replay.residuals(sm, plans, test, scale, rows_te)
        bar.update(1)
    g_tr, g_te = float((C.r0_tr ** 2).sum()), float((C.r0_te ** 2).sum())
    for r, a, b in zip(top, R_tr, R_te, strict=True):
        r["checked_train"] = 1 - float((a ** 2).sum()) / max(g_tr, 1e-300)
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
    """The ``n`` second effects whose joint linear fit with ``best`` removes most of the held-out
    gap: ``[((best, other), start params)]`` (start: the fitted single and the linear estimate).
    Pairs whose linear fit removes at least ``min_gain`` of what ``best``'s own linear fit leaves
    held out are proposed (the pair rule's ``pair_min``, to first order); where none does, the one
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
        params, _, l_te = linear_fit(C, sm, (best, other))
        if l_te < l_single:
            scored.append((l_te, other, params))
    scored.sort(key=lambda t: t[0])
    keep = [t for t in scored if l_single - t[0] >= min_gain * l_single][:n] or scored[:1]
    return [((best, o), {best: np.asarray(fitted[best], float), o: p[o]}) for _, o, p in keep]
