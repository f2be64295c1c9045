"""The diagnosis: where the sim-to-real gap lies, which effect causes it, how far it shrinks.

* **Where** (:func:`where`): every logged state is replayed one control period in the nominal
  simulator under the logged commands; the residual (logged minus predicted velocity change, per
  second) is decomposed per dof, per contact phase of each foot (swing, stance, touchdown,
  liftoff, estimated from foot heights since logs carry no forces), per base-speed and per
  joint-velocity bin, and over time; open-loop rollouts show how each dof diverges with horizon.
* **Which** (:func:`which`): each library effect is fitted on a training split of whole
  trajectories (:mod:`stride_jax.gap.fit`), pairs of the best few are fitted jointly, and all are
  scored on the held-out split: gap explained = 1 - held-out loss / nominal held-out loss, with a
  complexity penalty per parameter and bootstrap intervals over held-out trajectories. A fit with
  the wrong effect lowers the *training* loss too; only the held-out comparison chooses. Each
  candidate is checked to reproduce the nominal model at its nominal value.
* **Residual structure** (the library's limit): a ridge regression of the residual on state,
  command and contact features (:mod:`stride_jax.gap.linear_probe`, fitted on train, scored
  held-out) measures cheaply how much systematic gap is left after the best hypothesis. If much
  is left, the verdict is "unexplained by the library".
* **What is left, and where** (:mod:`stride_jax.gap.residual`): then a STRIDE residual -- a
  conditional flow-matching model of the generalised force the best hypothesis's simulator
  misses, given ``(q, qd, tau)`` -- is fitted on the training split and scored held-out (the
  one-step gap before and after adding its central sample), and its magnitude is decomposed per
  dof, per contact phase of each foot and per base-speed / joint-velocity / joint-position bin.
* **How far** (:func:`how_far`): one-step acceleration RMSE and ``horizon``-step rollout RMSE on
  held-out trajectories, nominal against the identified effect, with its parameter interval.

The noise floor of the one-step residual is estimated from its lag-1 autocovariance (white
velocity noise, differenced, gives a correlation of -1/2); the explained fraction is also given
relative to the gap above that floor.
"""

from __future__ import annotations

import dataclasses
import itertools
import time
from typing import Any

import numpy as np

from stride_jax.gap import effects, filters, fit, linear_probe, logs, regions, residual, sim
from stride_jax.gap.residual import ResidualConfig
from stride_jax.gap.regions import PHASES, dof_names, foot_phases, noise_floor  # noqa: F401 (re-exported)
from stride_jax.sim.model import SimModel

_rms = regions.rms


@dataclasses.dataclass(frozen=True)
class DiagnoseConfig:
    """Settings of a diagnosis (presets: :data:`PRESETS`).

    Attributes:
      holdout: fraction of trajectories held out for scoring (at least one).
      steps: control periods per replay in the fits and scores (multiple shooting; the "where"
        and the reported one-step RMSE always use one period).
      seed: of the split and the bootstraps.
      preprocess: cleaning of the logs before replay.
      fit: optimiser settings.
      pairs_of: fit pairs among this many best single effects (0: no pairs).
      penalty: complexity penalty per fitted parameter, in explained fraction.
      attribute_min: explained fraction (above the noise floor) needed to name an effect.
      significant: lower bootstrap bound of the explained fraction that counts as a real gap.
      structure_max: systematic residual left after the best hypothesis (linear probe, fraction of
        the nominal gap above the floor) beyond which the gap is "unexplained by the library".
      confident_p: bootstrap probability that the best beats the runner-up, for a confident call.
      horizon: open-loop rollout length (control steps).
      windows: rollout windows per trajectory.
      bins: bins of the velocity and time decompositions.
      exact_nominal: numerical precision below which (scaled RMS) the logs show no gap at all.
      block: length (control steps) of the held-out blocks that the tests resample (moving blocks
        within trajectories: the k-step residuals of neighbouring samples are correlated).
      boot: block-bootstrap resamples of the tests.
      alpha: family-wise level of the held-out tests (Bonferroni over the hypotheses compared).
      pair_min: a pair is preferred to the best single only if it removes at least this fraction
        of what the single leaves above the noise floor (and significantly more than nothing).
      residual: the STRIDE residual fitted on top of the best hypothesis (by default only when
        the verdict is "unexplained by the library"; :mod:`stride_jax.gap.residual`).
    """

    holdout: float = 0.34
    steps: int = 5
    seed: int = 0
    preprocess: filters.Preprocess = filters.Preprocess()
    fit: fit.FitConfig = fit.FitConfig()
    pairs_of: int = 3
    penalty: float = 0.005
    attribute_min: float = 0.5
    significant: float = 0.03
    structure_max: float = 0.15
    confident_p: float = 0.95
    horizon: int = 30
    windows: int = 3
    bins: int = 8
    exact_nominal: float = 1e-5
    block: int = 10
    boot: int = 2000
    alpha: float = 0.05
    pair_min: float = 0.1
    residual: ResidualConfig = ResidualConfig()


PRESETS = {
    "tiny": DiagnoseConfig(fit=fit.FitConfig(grid=7, profile=9, bootstrap=100, refits=0, max_nfev=8),
                           pairs_of=2, horizon=15, windows=2),
    "default": DiagnoseConfig(),
    # the Go1 benchmark on a 2-core CPU: shorter multiple-shooting horizon, coarser grids
    "fast": DiagnoseConfig(steps=3, fit=fit.FitConfig(grid=5, profile=5, bootstrap=100, refits=0, max_nfev=4),
                           pairs_of=2, horizon=10, windows=1),
}


# ----------------------------------------------------------------------------- helpers


def split(n: int, holdout: float, seed: int) -> tuple[list[int], list[int]]:
    """Whole trajectories into (train, held-out); needs at least 2."""
    if n < 2:
        raise ValueError(f"need at least 2 trajectories (train and held-out), got {n}")
    perm = np.random.default_rng(seed).permutation(n)
    k = min(max(1, int(round(holdout * n))), n - 1)
    return sorted(perm[k:].tolist()), sorted(perm[:k].tolist())


def scale_of(sm: SimModel, data: fit.Data) -> np.ndarray:
    """``[nv]`` spread of the logged velocity changes per second (floored)."""
    idx = fit.samples_before_next(data)
    dv = (data.target - data.qd[idx]) / (data.k * sm.robot.ctrl_dt)
    s = dv.std(0)
    return np.maximum(s, 1e-3 * max(float(s.max()), 1e-9))


def _boot_weights(n: int, B: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.multinomial(n, np.full(n, 1 / n), size=B).astype(float)  # [B, n]


# ----------------------------------------------------------------------------- where


def where(sm: SimModel, data: fit.Data, r: np.ndarray, scale: np.ndarray, cfg: DiagnoseConfig
          ) -> dict[str, Any]:
    """Decomposes the nominal one-step residual ``r [M, nv]`` (scaled) of ``data``."""
    names = dof_names(sm)
    idx = fit.samples_before_next(data)
    raw = r * scale  # rad/s^2 or m/s^2
    out: dict[str, Any] = {"dof_names": names,
                           "per_dof_rms": dict(zip(names, _rms(raw, 0).tolist())),
                           "per_dof_rms_scaled": dict(zip(names, _rms(r, 0).tolist())),
                           "scale": dict(zip(names, scale.tolist()))}
    total = _rms(r) + 1e-300
    # contact phases per foot
    phases = regions.sample_phases(sm, data)
    per_foot = {}
    for f, foot in enumerate(sm.robot.feet):
        leg = regions.leg_dofs(sm, foot.name)
        rows = {}
        for p, label in enumerate(PHASES):
            sel = phases[:, f] == p
            rows[label] = {"count": int(sel.sum()),
                           "rms_all": _rms(r[sel]) if sel.any() else None,
                           "rms_leg": _rms(r[sel][:, leg]) if sel.any() else None}
        per_foot[foot.name] = rows
    out["per_foot_phase"] = per_foot
    out["stance_fraction"] = {foot.name: float((phases[:, f] >= 1).mean())
                              for f, foot in enumerate(sm.robot.feet)}
    # base speed bins
    if sm.robot.floating_base:
        k, edges = regions.quantile_bins(regions.base_speed(data), cfg.bins)
        out["base_speed_bins"] = [{"lo": float(edges[i]), "hi": float(edges[i + 1]),
                                   "count": int((k == i).sum()), "rms": _rms(r[k == i])}
                                  for i in range(len(edges) - 1) if (k == i).any()]
    # joint velocity bins: signed mean and RMS of each actuated joint's own residual
    jv = {}
    for a, dof in enumerate(sm.act_dof):
        k, centres = regions.symmetric_bins(data.qd[idx, dof], cfg.bins)
        jv[names[dof]] = [{"centre": float(centres[i]), "count": int((k == i).sum()),
                           "mean": float(raw[k == i, dof].mean()) if (k == i).any() else None,
                           "rms": _rms(raw[k == i, dof]) if (k == i).any() else None}
                          for i in range(cfg.bins)]
    out["joint_velocity_bins"] = jv
    # over time (since the trajectory start)
    tloc = idx - data.bounds[data.traj]
    edges = np.linspace(0, tloc.max() + 1, cfg.bins + 1)
    k = np.clip(np.searchsorted(edges, tloc, side="right") - 1, 0, cfg.bins - 1)
    out["over_time"] = [{"t0_s": float(edges[i] * sm.robot.ctrl_dt), "t1_s": float(edges[i + 1] * sm.robot.ctrl_dt),
                         "rms": _rms(r[k == i]) if (k == i).any() else None} for i in range(cfg.bins)]
    out["rms_scaled"] = total
    return out


def divergence(sm: SimModel, plan: effects.Plan, data: fit.Data, cfg: DiagnoseConfig
               ) -> dict[str, Any]:
    """Open-loop rollout error per dof against horizon: ``rmse [H, ndof]`` (joints in rad, base
    position in m, base orientation angle in rad) over ``cfg.windows`` windows per trajectory."""
    H = cfg.horizon
    errs = []
    for i in range(data.n):
        a, b = data.bounds[i], data.bounds[i + 1]
        T = b - a
        if T <= H:
            continue
        starts = np.linspace(0, T - H - 1, cfg.windows).astype(int)
        q, _ = sim.rollout(sm, plan, data.q[a + starts], data.qd[a + starts], data.cmd[a:b], starts, H)
        ref = np.stack([data.q[a + s + 1:a + s + 1 + H] for s in starts])
        errs.append(_q_error(sm, q, ref))
    names = _q_names(sm)
    if not errs:
        return {"names": names, "rmse": None, "horizon": H}
    e = np.concatenate(errs)  # [W, H, nd]
    e = np.where(np.isfinite(e), e, 10.0)
    return {"names": names, "horizon": H, "rmse": np.sqrt((e ** 2).mean(0)).tolist(),
            "final_rmse": dict(zip(names, np.sqrt((e[:, -1] ** 2).mean(0)).tolist())),
            "windows": int(e.shape[0])}


def _q_names(sm: SimModel) -> list[str]:
    lay = logs.layout(sm)
    base = ["base_x", "base_y", "base_z", "base_angle"] if sm.robot.floating_base else []
    return base + list(lay.joints)


def _q_error(sm: SimModel, q: np.ndarray, ref: np.ndarray) -> np.ndarray:
    lay = logs.layout(sm)
    parts = []
    if sm.robot.floating_base:
        parts.append(q[..., :3] - ref[..., :3])
        dot = np.abs((q[..., 3:7] * ref[..., 3:7]).sum(-1)).clip(0, 1)
        parts.append(2 * np.arccos(dot)[..., None])
    parts.append(q[..., lay.qadr] - ref[..., lay.qadr])
    return np.concatenate(parts, -1)


# ----------------------------------------------------------------------------- which / how far


def check_nominal(sm: SimModel, data: fit.Data, scale: np.ndarray, r_nom: np.ndarray
                  ) -> dict[str, float]:
    """Max |residual change| of each candidate at its nominal value against the nominal model."""
    out = {}
    for e in effects.candidates(sm):
        r = fit.residual(sm, effects.build(sm, {e.name: np.asarray(e.nominal)}), data, scale)
        out[e.name] = float(np.abs(r - r_nom).max())
    return out


def _block_ids(data: fit.Data, length: int) -> tuple[np.ndarray, int]:
    """``[M]`` block index of each replayed sample (consecutive ``length`` control steps of one
    trajectory) and the number of blocks."""
    local = data.start - data.bounds[data.traj]
    key = data.traj.astype(np.int64) * 10 ** 7 + local // max(int(length), 1)
    _, ids = np.unique(key, return_inverse=True)
    return ids.ravel(), int(ids.max()) + 1


def _lower(x: np.ndarray, level: float) -> float:
    return float(np.quantile(x, min(max(level, 0.0), 1.0)))


def which(sm: SimModel, train: fit.Data, test: fit.Data, scale: np.ndarray, cfg: DiagnoseConfig,
          log=print) -> dict[str, Any]:
    """Fits every candidate on ``train``, then pairs of the best (unless the best single is exact),
    and scores all on ``test``.

    Held-out statistics resample blocks of ``cfg.block`` control steps within the held-out
    trajectories (``cfg.boot`` times, the same resamples for every hypothesis, so differences
    between hypotheses are paired). A pair replaces the best single only if (a) the paired
    bootstrap puts its held-out improvement over the single above zero at level ``alpha / pairs``
    and (b) it removes at least ``pair_min`` of what the single leaves above the noise floor.
    """
    nom = effects.build(sm)
    r_nom_tr = fit.residual(sm, nom, train, scale)
    r_nom_te = fit.residual(sm, nom, test, scale)
    M = len(r_nom_te)
    ids, nb = _block_ids(test, cfg.block)
    Wb = _boot_weights(nb, max(cfg.boot, cfg.fit.bootstrap or 0, 100), cfg.seed + 1)  # [B, nb]
    blocks = lambda r: np.bincount(ids, weights=(r ** 2).sum(1), minlength=nb)
    Lb_nom = blocks(r_nom_te)
    L_nom = float(Lb_nom.sum())
    boot_nom = np.maximum(Wb @ Lb_nom, 1e-300)
    fits: list[fit.Fit] = []
    r_te: dict[tuple, np.ndarray] = {}

    def score(f: fit.Fit) -> None:
        fits.append(f)
        r_te[f.names] = fit.residual(sm, effects.build(sm, f.params), test, scale)

    for e in effects.candidates(sm):
        t0 = time.time()
        f = fit.fit(sm, train, scale, (e.name,), cfg.fit)
        score(f)
        log(f"  fit {e.name:17s} {_fmt(f.params)}  train loss {f.train_loss:.4g}  ({f.evals} evals, "
            f"{time.time() - t0:.1f} s)")
    n_single = len(fits)
    singles = {f.names[0]: f for f in fits}
    held = lambda names: float((r_te[names] ** 2).sum())
    ranked = sorted(fits, key=lambda f: held(f.names))
    best_single = ranked[0]
    exact = held(best_single.names) <= 1e-8 * L_nom
    if not exact and cfg.pairs_of >= 2:
        # pairs: the best few singles with each other, and the best single with the effects that
        # most lower the training loss on top of it (a conditional grid screen: an effect that is
        # weak alone, e.g. a delay masked by damping, can still be the missing second one)
        S0 = best_single.names[0]
        screen = []
        for e in effects.candidates(sm):
            if e.name == S0 or e.size != 1:
                continue
            lo, hi = (float(b[0]) for b in e.bounds(sm))
            xs = (np.arange(int(lo), int(hi) + 1, max(1, int(hi - lo) // 15)) if e.integer
                  else np.linspace(lo, hi, cfg.fit.grid))
            obj = fit.Objective(sm, train, scale, (e.name,), base=best_single.params)
            tot = [obj.losses(np.array([float(x)])).sum() for x in xs]
            screen.append((min(tot), e.name, float(xs[int(np.argmin(tot))])))
        screen.sort()
        pairs = list(itertools.combinations([f.names[0] for f in ranked[:cfg.pairs_of]], 2))
        pairs += [(S0, n) for _, n, _ in screen[:cfg.pairs_of - 1]]
        seen = set()
        for a, b in pairs:
            if frozenset((a, b)) in seen:
                continue
            seen.add(frozenset((a, b)))
            start = singles[a].params | singles[b].params
            for _, n, x in screen:
                if (a, b) == (S0, n):
                    start[n] = np.array([x])
            t0 = time.time()
            f = fit.fit(sm, train, scale, (a, b), cfg.fit, start)
            score(f)
            log(f"  fit {a}+{b}: {_fmt(f.params)}  ({f.evals} evals, {time.time() - t0:.1f} s)")
    rows = []
    for f in fits:
        Lb = blocks(r_te[f.names])
        k = sum(effects.ALL[n].size for n in f.names)
        expl = 1 - Lb.sum() / max(L_nom, 1e-300)
        boot = 1 - (Wb @ Lb) / boot_nom
        rows.append({"effects": list(f.names), "params": _jsonable(f.params), "param_lo": _jsonable(f.lo),
                     "param_hi": _jsonable(f.hi), "n_params": k, "train_loss": f.train_loss,
                     "heldout_loss": float(Lb.sum()), "explained": float(expl),
                     "explained_ci": np.percentile(boot, [5, 95]).tolist(),
                     "p_no_better_than_nominal": float((boot <= 0).mean()),
                     "score": float(expl - cfg.penalty * k), "_boot": boot})
    rows.sort(key=lambda r: -r["score"])
    single_rows = [r for r in rows if len(r["effects"]) == 1]
    pair_rows = [r for r in rows if len(r["effects"]) == 2]
    S = single_rows[0]
    r_S = r_te[tuple(S["effects"])]
    floor_S = noise_floor(r_S, test)
    left_S = max(S["heldout_loss"] / M - floor_S, 0.0)  # mean squared residual above the floor
    pair_tests = []
    for P in pair_rows:
        gain = (S["heldout_loss"] - P["heldout_loss"]) / M
        d = P["_boot"] - S["_boot"]  # paired: explained(pair) - explained(single)
        lo = _lower(d, cfg.alpha / max(len(pair_rows), 1))
        ok = bool(lo > 0 and gain >= cfg.pair_min * left_S and gain > 1e-6 * L_nom / M)
        pair_tests.append({"pair": P["effects"], "single": S["effects"], "gain_explained": float(gain * M / L_nom),
                           "gain_lower": lo, "fraction_of_left": float(gain / max(left_S, 1e-300)),
                           "preferred": ok})
        P["vs_best_single"] = pair_tests[-1]
    chosen = max((P for P, t in zip(pair_rows, pair_tests) if t["preferred"]),
                 key=lambda r: r["explained"], default=S)
    rows.remove(chosen)
    rows.insert(0, chosen)
    # bootstrap probability that the chosen hypothesis beats the runner-up (for a chosen single:
    # by penalised score, against the best hypothesis that is not a superset of it; for a chosen
    # pair: unpenalised, against the best single)
    for i, row in enumerate(rows):
        if i == 0 and len(row["effects"]) == 2:
            other = S
            row["p_beats_next"] = float((row["_boot"] > other["_boot"]).mean())
            continue
        others = [r for r in rows if r is not row and not set(row["effects"]) < set(r["effects"])]
        if not others:
            row["p_beats_next"] = 1.0
            continue
        other = others[0]
        s_self = row["_boot"] - cfg.penalty * row["n_params"]
        s_other = other["_boot"] - cfg.penalty * other["n_params"]
        row["p_beats_next"] = float((s_self > s_other).mean())
    # detection: is the best hypothesis better than the nominal model on data it was not fitted
    # on? Cross-fitting: the held-out split scored with the training fit, and the training split
    # scored with a refit on the held-out split (every trajectory is held-out once). One-sided
    # test at level alpha / (hypotheses compared), for the selection.
    best = rows[0]
    n_hyp = len(rows)
    bnames = tuple(best["effects"])
    start = {k: np.asarray(v) for k, v in best["params"].items()}
    if exact:
        swap_params = start
    else:
        f_sw = fit.fit(sm, test, scale, bnames, dataclasses.replace(cfg.fit, profile=0, refits=0), start)
        swap_params = f_sw.params
    r_sw_tr = fit.residual(sm, effects.build(sm, swap_params), train, scale)
    ids_tr, nb_tr = _block_ids(train, cfg.block)
    Lb_all_nom = np.concatenate([Lb_nom, np.bincount(ids_tr, weights=(r_nom_tr ** 2).sum(1), minlength=nb_tr)])
    Lb_all_best = np.concatenate([blocks(r_te[bnames]),
                                  np.bincount(ids_tr, weights=(r_sw_tr ** 2).sum(1), minlength=nb_tr)])
    Wa = _boot_weights(len(Lb_all_nom), len(Wb), cfg.seed + 3)
    cf_boot = 1 - (Wa @ Lb_all_best) / np.maximum(Wa @ Lb_all_nom, 1e-300)
    detect_lower = _lower(cf_boot, cfg.alpha / n_hyp)
    # sign-flip test of the paired block improvements (nominal minus best): under "no gap" the
    # fitted effect helps and hurts alike; blocks it leaves unchanged carry no weight, which keeps
    # the test sharp for effects that act rarely (saturation, dead band)
    d = Lb_all_nom - Lb_all_best
    flips = np.random.default_rng(cfg.seed + 4).choice([-1.0, 1.0], size=(max(cfg.boot, 1000) * 2, len(d)))
    p_flip = float((1 + ((flips @ d) >= d.sum() - 1e-12 * np.abs(d).sum()).sum()) / (1 + len(flips)))
    detection = {"explained_crossfit": float(1 - Lb_all_best.sum() / max(Lb_all_nom.sum(), 1e-300)),
                 "explained_lower": detect_lower, "p_value": p_flip, "significant": bool(p_flip < cfg.alpha / n_hyp),
                 "level": cfg.alpha / n_hyp, "hypotheses": n_hyp,
                 "blocks": int(len(Lb_all_nom)), "resamples": int(len(Wa)),
                 "swapped_fit": _jsonable(swap_params)}
    # rivals the held-out data cannot tell apart from the best: other effects (neither a subset
    # nor a superset) that match or beat it in at least alpha of the paired resamples
    for row in rows[1:]:
        row["p_matches_best"] = float((row["_boot"] >= best["_boot"] - 1e-12).mean())
    # residual structure left: linear probe on the nominal and on the best hypothesis
    plan_best = effects.build(sm, {k: np.asarray(v) for k, v in best["params"].items()})
    r_best_tr = fit.residual(sm, plan_best, train, scale)
    r_best_te = r_te[tuple(best["effects"])]
    floor = noise_floor(r_best_te, test)
    g_nom = fit.gap(r_nom_te)
    g_best = fit.gap(r_best_te)
    above = max(g_nom - floor, 1e-300)
    pr_nom = linear_probe.probe(sm, train, r_nom_tr, test, r_nom_te)
    pr_best = linear_probe.probe(sm, train, r_best_tr, test, r_best_te)
    probe_nom = 1 - fit.gap(pr_nom) / max(g_nom, 1e-300)
    left = max(g_best - fit.gap(pr_best), 0.0) / above
    hints = linear_probe.structure_hints(sm, train, r_best_tr, test, r_best_te)
    for row in rows:
        row["explained_above_floor"] = float(min(1.0, (g_nom - row["heldout_loss"] / M) / above))
        del row["_boot"]
    return {"ranking": rows, "nominal_heldout_loss": L_nom, "noise_floor": floor,
            "gap_ms": g_nom, "probe_explained_nominal": probe_nom, "structure_left": left,
            "detection": detection,
            "structure_hints": hints, "pair_tests": pair_tests, "best_single": S["effects"], "singles_fitted": n_single,
            "residual_after_best": {"per_dof_rms_scaled": _rms(r_best_te, 0).tolist()},
            "r_nom_test": r_nom_te, "r_best_test": r_best_te, "plan_best": plan_best}


def verdict(w: dict[str, Any], cfg: DiagnoseConfig) -> dict[str, Any]:
    """The answer to "which": ``no significant gap``, ``explained`` (by the best hypothesis, with
    ``confident`` True/False) or ``unexplained by the library``.

    A gap is significant when the best hypothesis beats the nominal model on cross-fitted held-out
    data in a one-sided sign-flip test of block improvements (``w["detection"]``, level
    ``alpha`` / hypotheses) or the linear probe explains more than
    ``cfg.significant`` of the held-out residual."""
    best = w["ranking"][0]
    det = w["detection"]
    significant = det["significant"] or w["probe_explained_nominal"] > cfg.significant
    if not significant:
        return {"verdict": "no significant gap", "effects": [], "confident": False,
                "reason": f"best candidate explains {best['explained']:.1%} of the held-out gap, cross-fitted "
                          f"{det['explained_crossfit']:.2%} (sign-flip p = {det['p_value']:.3g}, needs < "
                          f"{det['level']:.3g}; one-sided {1 - det['level']:.2%} bootstrap bound "
                          f"{det['explained_lower']:.2%}); linear probe "
                          f"{w['probe_explained_nominal']:.1%}"}
    # hypotheses the held-out data cannot tell apart from the best (other effects, paired bootstrap)
    ties = ["+".join(r["effects"]) for r in w["ranking"][1:]
            if r.get("p_matches_best", 0.0) >= cfg.alpha and set(r["effects"]) - set(best["effects"])
            and not set(best["effects"]) < set(r["effects"]) and not set(r["effects"]) < set(best["effects"])]
    explained = best["explained_above_floor"] >= cfg.attribute_min
    pair_note = ""
    if len(best["effects"]) == 2:
        t = best["vs_best_single"]
        pair_note = (f"; the pair beats the best single ({'+'.join(t['single'])}) by {t['gain_explained']:.2%} of the "
                     f"gap (lower bound {t['gain_lower']:.2%}), {t['fraction_of_left']:.0%} of what the single leaves "
                     f"above the noise floor")
    hint = ""
    h = (w.get("structure_hints") or [None])[0]
    # structure as a fraction of the nominal gap above the noise floor (noise would hide it when
    # measured against the whole residual left)
    above = max(w["gap_ms"] - w["noise_floor"], 1e-300)
    left_ms = w["gap_ms"] * (1 - best["explained"])
    if h and best["explained"] < 0.999 and h["explained"] * left_ms / above > 0.01:
        hint = (f"; the fit leaves structure: {h['feature']} alone explains {h['explained']:.1%} of the residual "
                f"left after it ({h['explained'] * left_ms / above:.1%} of the gap above the noise floor; "
                f"held-out linear probe)")
    if explained and w["structure_left"] <= cfg.structure_max:
        confident = (best["explained_ci"][0] >= cfg.attribute_min * (1 - w["noise_floor"] / max(w["gap_ms"], 1e-300))
                     and best["p_beats_next"] >= cfg.confident_p and not ties and not hint)
        return {"verdict": "explained", "effects": best["effects"], "confident": bool(confident),
                "indistinguishable_from": ties,
                "reason": f"{'+'.join(best['effects'])} explains {best['explained']:.1%} of the held-out gap "
                          f"({best['explained_above_floor']:.1%} above the noise floor), beats the runner-up "
                          f"in {best['p_beats_next']:.0%} of resamples; structure left {w['structure_left']:.1%}"
                          + pair_note + hint
                          + (f"; indistinguishable on these logs from {', '.join(ties)}" if ties else "")}
    return {"verdict": "unexplained by the library", "effects": best["effects"], "confident": False,
            "reason": f"best ({'+'.join(best['effects'])}) explains {best['explained_above_floor']:.1%} above the "
                      f"noise floor; systematic residual left (linear probe) {w['structure_left']:.1%} of the gap" + hint}


def how_far(sm: SimModel, test: fit.Data, scale: np.ndarray, w: dict[str, Any], cfg: DiagnoseConfig
            ) -> dict[str, Any]:
    """Held-out gap before and after the best hypothesis: one-step acceleration RMSE per dof and
    overall (``test`` holds one-step replays), the fit's ``k``-step gap, ``horizon``-step rollout
    RMSE per dof."""
    names = dof_names(sm)
    nom = effects.build(sm)
    r0 = fit.residual(sm, nom, test, scale)
    r1 = fit.residual(sm, w["plan_best"], test, scale)
    div0 = divergence(sm, nom, test, cfg)
    div1 = divergence(sm, w["plan_best"], test, cfg)
    g0, g1 = fit.gap(r0), fit.gap(r1)
    k0, k1 = fit.gap(w["r_nom_test"]), fit.gap(w["r_best_test"])
    return {"one_step_acc_rmse_before": dict(zip(names, _rms(r0 * scale, 0).tolist())),
            "one_step_acc_rmse_after": dict(zip(names, _rms(r1 * scale, 0).tolist())),
            "gap_before": g0, "gap_after": g1, "shrink": 1 - g1 / max(g0, 1e-300),
            "kstep_gap_before": k0, "kstep_gap_after": k1, "kstep_shrink": 1 - k1 / max(k0, 1e-300),
            "rollout_before": div0, "rollout_after": div1,
            "rollout_final_rmse_mean_before": _mean_final(div0),
            "rollout_final_rmse_mean_after": _mean_final(div1)}


def _mean_final(div):
    return None if div["rmse"] is None else float(np.mean(list(div["final_rmse"].values())))


def _jsonable(d: dict) -> dict:
    return {k: np.asarray(v, float).round(6).tolist() for k, v in d.items()}


def _fmt(params: dict) -> str:
    return ", ".join(f"{k}={np.array2string(np.asarray(v), precision=4)}" for k, v in params.items())


# ----------------------------------------------------------------------------- top level


def diagnose(sm: SimModel, trajs: list[logs.Trajectory], cfg: DiagnoseConfig = DiagnoseConfig(),
             log=print) -> dict[str, Any]:
    """Runs where / which / how far on logged trajectories. Returns a JSON-able dict (plus a few
    arrays under keys starting with ``_`` for the plots)."""
    t_start = time.time()
    dt = sm.robot.ctrl_dt
    prep = [filters.preprocess(tr, dt, cfg.preprocess) for tr in trajs]
    trajs = [p[0] for p in prep]
    tr_idx, te_idx = split(len(trajs), cfg.holdout, cfg.seed)
    data = fit.make_data(trajs)
    train, test = fit.subset(data, tr_idx), fit.subset(data, te_idx)
    scale = scale_of(sm, train)
    train_k, test_k = (fit.make_data([trajs[i] for i in ix], cfg.steps) for ix in (tr_idx, te_idx))
    nom = effects.build(sm)
    r_all = fit.residual(sm, nom, data, scale)
    log(f"{sm.robot.name}: {len(trajs)} trajectories ({len(tr_idx)} train, {len(te_idx)} held out), "
        f"{len(r_all)} one-step replays; nominal scaled RMS residual {_rms(r_all):.4g}")
    out: dict[str, Any] = {
        "robot": sm.robot.name, "n_trajectories": len(trajs), "train": [data.names[i] for i in tr_idx],
        "heldout": [data.names[i] for i in te_idx], "n_samples": int(len(r_all)),
        "config": dataclasses.asdict(cfg),
        "preprocess": {"outliers_replaced": int(sum(p[1]["outliers_replaced"] for p in prep)),
                       "smoothing_bandwidth_hz": cfg.preprocess.bandwidth_hz(dt)},
        "residual_definition": "(logged next velocity - nominal one-step prediction) / control period; "
                               "'scaled' divides each dof by the spread of its logged velocity changes",
    }
    out["where"] = where(sm, data, r_all, scale, cfg)
    if _rms(r_all) < cfg.exact_nominal:
        out["nominal_check"] = {}
        out["verdict"] = {"verdict": "no significant gap", "effects": [], "confident": True,
                          "reason": f"the nominal model replays the logs to numerical precision "
                                    f"(scaled RMS {_rms(r_all):.2g})"}
        out["which"], out["how_far"], out["residual"] = None, None, None
        out["seconds"] = time.time() - t_start
        return out
    out["nominal_check"] = check_nominal(sm, test_k, scale, fit.residual(sm, nom, test_k, scale))
    bad = {k: v for k, v in out["nominal_check"].items() if v > 1e-9}
    if bad:
        raise RuntimeError(f"effects do not reproduce the nominal model at their nominal value: {bad}")
    w = which(sm, train_k, test_k, scale, cfg, log)
    out["verdict"] = verdict(w, cfg)
    out["how_far"] = how_far(sm, test, scale, w, cfg)
    out["residual"] = None
    if cfg.residual.wanted(out["verdict"]["verdict"]):
        out["residual"] = residual.fit_on_top(sm, w["plan_best"], train, test, scale, cfg.residual,
                                              cfg.bins, log)
        out["residual"]["on_top_of"] = out["verdict"]["effects"]
        out["verdict"]["reason"] += residual.reason(out["residual"])
    out["which"] = {k: v for k, v in w.items() if k not in ("r_nom_test", "r_best_test", "plan_best")}
    out["where"]["divergence"] = out["how_far"]["rollout_before"]
    out["seconds"] = time.time() - t_start
    log(f"verdict: {out['verdict']['verdict']} {out['verdict']['effects']} — {out['verdict']['reason']}")
    return out
