"""Which effect causes the gap, and the verdict (the diagnosis's second question).

:func:`which` fits every library effect on a training split of whole trajectories
(:mod:`stride_jax.gap.fit`), pairs of the best few jointly, and scores all on the held-out split:
gap explained = 1 - held-out loss / nominal held-out loss, with a complexity penalty per
parameter and block-bootstrap intervals over the held-out trajectories (a fit with the wrong
effect lowers the *training* loss too; only the held-out comparison chooses). It also tests
detection by cross-fitting and measures the systematic structure left after the best hypothesis
with a linear probe (:mod:`stride_jax.gap.linear_probe`). :func:`verdict` turns that into
"no significant gap", "explained" (confident or not) or "unexplained by the library".
:func:`check_nominal` checks that every candidate reproduces the nominal model at its nominal
value.
"""

from __future__ import annotations

import dataclasses
import itertools
import time
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy import stats

from stride_jax.gap import (admit, effects, fit, form, granularity, linear_probe, nominal, progress, regions,
                            replay, sim)
from stride_jax.gap.regions import noise_floor
from stride_jax.gap.screen import fit_stride_of
from stride_jax.sim.model import SimModel

if TYPE_CHECKING:
    from stride_jax.gap.diagnose import DiagnoseConfig

_rms = regions.rms


def _boot_weights(n: int, B: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.multinomial(n, np.full(n, 1 / n), size=B).astype(float)  # [B, n]


def check_nominal(sm: SimModel, data: fit.Data, scale: np.ndarray, r_nom: np.ndarray
                  ) -> dict[str, float]:
    """Max |residual change| of each candidate at its nominal value against the nominal model."""
    cands = effects.candidates(sm)
    R = replay.residuals(sm, [effects.build(sm, {e.name: np.asarray(e.nominal)}) for e in cands], data, scale)
    return {e.name: float(np.abs(r - r_nom).max()) for e, r in zip(cands, R, strict=True)}


def _block_ids(data: fit.Data, length: int) -> tuple[np.ndarray, int]:
    """``[M]`` block index of each replayed sample (consecutive ``length`` control steps of one
    trajectory) and the number of blocks."""
    ids, nb, _ = fit.block_ids(data, length)
    return ids, nb


def _lower(x: np.ndarray, level: float) -> float:
    return float(np.quantile(x, min(max(level, 0.0), 1.0)))


def _with_interval(sm: SimModel, train: fit.Data, scale: np.ndarray, row: dict, cfg: DiagnoseConfig,
                   cache: dict | None = None) -> None:
    """Gives a ranking row fitted without its interval (:func:`stride_jax.gap.fit.with_interval`) one."""
    if not row["interval"]:
        f = fit.with_interval(sm, train, scale, row["_fit"], cfg.fit, cache=cache)
        row.update(param_lo=_jsonable(f.lo), param_hi=_jsonable(f.hi), interval=True, _fit=f)


FAR_BEHIND = 4.0
"""A shortlisted single whose best grid node's training loss is this many times the best single
fitted before it keeps that node (no line search: ``Fit.grid_only``). A line search moves the
loss within one grid cell, and on the Go1's 12 x 8 s case the three singles it skipped (damping,
frictionloss@calf, kp_scale@calf) were 7-10x behind damping@calf after theirs; should a
grid-only single lead on the held-out split all the same, it is fitted in full."""


def which(sm: SimModel, train: fit.Data, test: fit.Data, scale: np.ndarray, cfg: DiagnoseConfig,
          log=print, singles: list[str] | None = None, pair_screen=None, nuisance=None,
          hints: dict | None = None) -> dict[str, Any]:
    """Fits every candidate on ``train``, then pairs of the best (unless the best single is exact),
    and scores all on ``test``.

    Held-out statistics resample blocks of ``cfg.block`` control steps within the held-out
    trajectories (``cfg.boot`` times, the same resamples for every hypothesis, so differences
    between hypotheses are paired). A pair replaces the best single only if (a) the paired
    bootstrap puts its held-out improvement over the single above zero at level ``alpha / pairs``
    and (b) it removes at least ``pair_min`` of what the single leaves above the noise floor and
    (c) at least ``pair_material`` of the whole held-out gap above the floor, or, below (c), its
    second effect is a confounder of the single's estimate (``pair_confounds``); a hypothesis holding an
    effect that overlaps the simulator's contact settings must beat re-fitting them instead
    (``nuisance``: a :class:`stride_jax.gap.nuisance.Null`, or None; :mod:`stride_jax.gap.admit`).

    ``singles``: the effects to fit alone (default: every library candidate; the screen's
    shortlist, :mod:`stride_jax.gap.screen`); ``hints``: their screen's linear estimates (name ->
    parameters), which a scalar's grid holds as well. ``pair_screen(best_single_name, fits_by_name) ->
    [((a, b), start)]``: the pairs to fit (default: the best ``pairs_of`` singles with each other
    and a conditional grid screen on top of the best). A finer variant ranks above its all-joints
    effect only by the margin rule of :func:`stride_jax.gap.granularity.prefer_coarse`.
    """
    unstable0 = sim.unstable()
    clock = [("start", time.time())]  # the stages' seconds, for the record (``seconds``)
    nom = effects.build(sm)
    r_nom_tr = fit.residual(sm, nom, train, scale)
    r_nom_te = fit.residual(sm, nom, test, scale)
    M = len(r_nom_te)
    ids, nb = _block_ids(test, cfg.block)
    Wb = _boot_weights(nb, max(cfg.boot, 100), cfg.seed + 1)  # [B, nb]
    blocks = lambda r: np.bincount(ids, weights=(r ** 2).sum(1), minlength=nb)
    Lb_nom = blocks(r_nom_te)
    L_nom = float(Lb_nom.sum())
    boot_nom = np.maximum(Wb @ Lb_nom, 1e-300)
    fits: list[fit.Fit] = []
    r_te: dict[tuple, np.ndarray] = {}
    # every training replay of the fits (keyed by effects and parameters), shared by the singles,
    # the pairs, the intervals and the form check (:func:`check_form`): an interval's centre and
    # the form check's grid are replays the singles' fits made already
    replays: dict = {}

    def score(f: fit.Fit) -> None:
        fits.append(f)
        r_te[f.names] = fit.residual(sm, effects.build(sm, f.params), test, scale)

    names = [e.name for e in effects.candidates(sm)] if singles is None else list(singles)
    for name in progress.track(names, "fits: each shortlisted effect alone", cfg.progress):
        t0 = time.time()
        start = {name: hints[name]} if hints and name in hints else None
        far = FAR_BEHIND * min(f.train_loss for f in fits) if fits else None
        f = fit.fit(sm, train, scale, (name,), cfg.fit, start, interval=False, cache=replays,  # intervals: below
                    grid_only_above=far)
        score(f)
        log(f"  fit {name:17s} {_fmt(f.params)}  train loss {f.train_loss:.4g}  ({f.evals} evals, "
            f"{time.time() - t0:.1f} s{'; grid only: far behind' if f.grid_only else ''})")
    held = lambda names: float((r_te[names] ** 2).sum())
    first = min(fits, key=lambda f: held(f.names))
    if first.grid_only:  # a single left on its grid that leads all the same is fitted in full
        fits.remove(first)
        score(fit.fit(sm, train, scale, first.names, cfg.fit, first.params, interval=False, cache=replays))
        log(f"  fit {first.names[0]:17s} {_fmt(fits[-1].params)}  (left on its grid, leads held out: fitted in full)")
    lead = min(fits, key=lambda f: held(f.names)).names[0]
    coarse = granularity.coarse_of(sm, lead)  # the finer choice needs the best's all-joints rival
    if coarse and coarse not in [f.names[0] for f in fits]:
        score(fit.fit(sm, train, scale, (coarse,), cfg.fit, interval=False, cache=replays))
        log(f"  fit {coarse:17s} {_fmt(fits[-1].params)}  (the all-joints rival of {lead})")
    n_single = len(fits)
    clock.append(("singles", time.time()))
    # intervals only where reported: pairs (their fits give them), the best single (a pair's
    # estimates are weighed against it) and the named hypothesis, below; other singles' rows
    # report none (``interval`` False)
    singles = {f.names[0]: f for f in fits}
    ranked = sorted(fits, key=lambda f: held(f.names))
    best_single = ranked[0]
    exact = held(best_single.names) <= 1e-8 * L_nom
    screen_unstable = 0
    proposals = []  # ((a, b), start)
    if not exact and cfg.pairs_of >= 2 and pair_screen is not None:
        proposals = pair_screen(best_single.names[0], {k: v.params[k] for k, v in singles.items()})
    elif not exact and cfg.pairs_of >= 2:
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
            screen_unstable += obj.unstable
            screen.append((min(tot), e.name, float(xs[int(np.argmin(tot))])))
        screen.sort()
        pairs = list(itertools.combinations([f.names[0] for f in ranked[:cfg.pairs_of]], 2))
        pairs += [(S0, n) for _, n, _ in screen[:cfg.pairs_of - 1]]
        for a, b in pairs:
            start = {k: v for n in (a, b) if n in singles for k, v in singles[n].params.items()}
            for _, n, x in screen:
                if (a, b) == (S0, n):
                    start[n] = np.array([x])
            proposals.append(((a, b), start))
    seen = set()
    proposals = [(ab, st) for ab, st in proposals if not (frozenset(ab) in seen or seen.add(frozenset(ab)))]
    for (a, b), start in progress.track(proposals, "fits: pairs", cfg.progress):
        t0 = time.time()
        f = fit.fit(sm, train, scale, (a, b), cfg.fit, start, cache=replays)
        score(f)
        log(f"  fit {a}+{b}: {_fmt(f.params)}  ({f.evals} evals, {time.time() - t0:.1f} s)")
    # a pair that moves an integer effect (a delay) off its single's value: the same pair with the
    # integer held at the single's value (its fit is one of the pair's own, Fit.integer_fits),
    # scored held out for the pair rule's trade test (:func:`stride_jax.gap.admit.pair_tests`)
    held_at_single = {}
    for f in fits[n_single:]:
        for n in f.names:
            if f.integer_fits and n in singles:
                v = float(singles[n].params[n][0])
                if v != float(f.params[n][0]) and v in f.integer_fits:
                    params = f.integer_fits[v][0]
                    held_at_single[f.names] = (n, v, params, fit.residual(sm, effects.build(sm, params), test, scale))
    clock.append(("pairs", time.time()))
    rows = []
    for f in fits:
        Lb = blocks(r_te[f.names])
        k = sum(effects.ALL[n].size for n in f.names)
        expl = 1 - Lb.sum() / max(L_nom, 1e-300)
        boot = 1 - (Wb @ Lb) / boot_nom
        rows.append({"effects": list(f.names), "params": _jsonable(f.params), "param_lo": _jsonable(f.lo),
                     "param_hi": _jsonable(f.hi), "interval": len(f.names) > 1 or not cfg.fit.profile,
                     "_fit": f, "at_bound": _at_bound(f), "unstable_evals": f.unstable, "grid_only": f.grid_only,
                     "n_params": k, "train_loss": f.train_loss,
                     "heldout_loss": float(Lb.sum()), "explained": float(expl),
                     "explained_ci": np.percentile(boot, [5, 95]).tolist(),
                     "p_no_better_than_nominal": float((boot <= 0).mean()),
                     "score": float(expl - cfg.penalty * k), "_boot": boot})
        if f.names in held_at_single:
            n, v, params, r = held_at_single[f.names]
            Lc = blocks(r)
            rows[-1]["_held_at_single"] = {"effect": n, "value": v, "params": _jsonable(params),
                                           "heldout_loss": float(Lc.sum()),
                                           "explained": float(1 - Lc.sum() / max(L_nom, 1e-300)),
                                           "_boot": 1 - (Wb @ Lc) / boot_nom}
    rows.sort(key=lambda r: -r["score"])
    granularity.prefer_coarse(rows, cfg.screen.finer_margin, cfg.alpha, lambda n: noise_floor(r_te[n], test) * M / L_nom)
    _with_interval(sm, train, scale, next(r for r in rows if len(r["effects"]) == 1), cfg, replays)
    _, S, pair_tests, nuisance_tests = admit.choose(rows, r_te, test, M, L_nom, blocks, Wb, boot_nom, cfg,
                                                    nuisance)
    _with_interval(sm, train, scale, rows[0], cfg, replays)  # the named hypothesis always has its interval
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
    clock.append(("choice", time.time()))  # the ranking, the nuisance tests and the intervals
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
        thin = fit.thin(test, fit_stride_of(cfg.screen, len(test.start)))
        f_sw = fit.fit(sm, thin, scale, bnames, dataclasses.replace(cfg.fit, profile=0, refits=0), start)
        swap_params = f_sw.params
    r_sw_tr = fit.residual(sm, effects.build(sm, swap_params), train, scale)
    ids_tr, nb_tr = _block_ids(train, cfg.block)
    clock.append(("crossfit", time.time()))
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
    # the Monte Carlo p-value stops at 1 / (1 + flips); the normal approximation of the sign-flip
    # distribution (mean 0, variance sum d^2) tells apart the gaps beyond that floor
    z = float(d.sum() / np.sqrt(max(float((d ** 2).sum()), 1e-300)))
    detection = {"explained_crossfit": float(1 - Lb_all_best.sum() / max(Lb_all_nom.sum(), 1e-300)),
                 "explained_lower": detect_lower, "p_value": p_flip, "significant": bool(p_flip < cfg.alpha / n_hyp),
                 "p_floor": 1 / (1 + len(flips)), "z": z, "p_normal": float(stats.norm.sf(z)),
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
        del row["_boot"], row["_fit"]
        row.pop("_held_at_single", None)
    u1 = sim.unstable()
    unstable = {"fits": int(sum(f.unstable for f in fits)), "pair_screen": int(screen_unstable),
                "diverged_replays": u1["diverged"] - unstable0["diverged"],
                "mujoco_warnings": u1["warnings"] - unstable0["warnings"]}
    return {"ranking": rows, "nominal_heldout_loss": L_nom, "noise_floor": floor, "unstable": unstable,
            "gap_ms": g_nom, "probe_explained_nominal": probe_nom, "structure_left": left,
            "detection": detection,
            "structure_hints": hints, "pair_tests": pair_tests, "nuisance_tests": nuisance_tests,
            "form_check": None,  # check_form's, run only where it could decide (diagnose)
            "best_single": S["effects"], "singles_fitted": n_single,
            "seconds": {b[0]: round(b[1] - a[1], 2) for a, b in zip(clock, clock[1:] + [("rest", time.time())])},
            "residual_after_best": {"per_dof_rms_scaled": _rms(r_best_te, 0).tolist()},
            "r_nom_test": r_nom_te, "r_best_test": r_best_te, "plan_best": plan_best,
            "_train": train, "_replays": replays}


def check_form(sm: SimModel, train: fit.Data, scale: np.ndarray, w: dict[str, Any], v: dict[str, Any],
               cfg: DiagnoseConfig, log=print) -> dict[str, Any] | None:
    """The named single's form (:func:`stride_jax.gap.form.check`: one value where each joint moves
    slowest and where it moves fastest), run only where it can decide: the verdict ``v`` is a
    confident single (the check costs two fits and can only take confidence away). Sets
    ``w["form_check"]``."""
    best = w["ranking"][0]
    w["form_check"] = None
    if not (cfg.form_tol > 0 and v["verdict"] == "explained" and v["confident"] and len(best["effects"]) == 1):
        return None
    t0 = time.time()
    shared = w.get("_replays") if train is w.get("_train") else None  # which()'s replays of the same data
    c = w["form_check"] = form.check(sm, train, scale, best, cfg.fit, cfg.form_tol, cache=shared)
    if c:
        log(f"  form check {best['effects'][0]}: where each joint moves slowest {c['slow']}, fastest {c['fast']} "
            f"({'differ' if c['differs'] else 'agree'}; {time.time() - t0:.1f} s)")
    return c


def _ties(w: dict[str, Any], cfg: DiagnoseConfig) -> list[str]:
    """Hypotheses the held-out data cannot tell apart from the best: other effects (neither a
    subset nor a superset) that match or beat it in at least ``alpha`` of the paired resamples."""
    best = w["ranking"][0]
    return ["+".join(r["effects"]) for r in w["ranking"][1:]
            if r.get("p_matches_best", 0.0) >= cfg.alpha and set(r["effects"]) - set(best["effects"])
            and not set(best["effects"]) < set(r["effects"]) and not set(r["effects"]) < set(best["effects"])]


def bound_note(row: dict[str, Any]) -> str:
    """"; at the bound: ..." for the parameters of a ranking row whose estimate sits on a bound
    (other than its nominal value), or ""."""
    hits = [f"{n} = {_num(row['params'][n][i])}" + (f" ({effects.ALL[n].labels[i]})" if len(row["params"][n]) > 1 else "")
            for n, flags in row.get("at_bound", {}).items() for i, f in enumerate(flags) if f]
    return (f"; at the bound: {', '.join(hits)} (the fit stopped at the parameter's bound: the true value may lie "
            f"beyond it, or another effect is being imitated)") if hits else ""


def admission_note(w: dict[str, Any], cfg: DiagnoseConfig) -> str:
    """What the pair and nuisance rules (:mod:`stride_jax.gap.admit`) decided about the hypotheses
    ranked above or on top of the named one, as clauses of the reason ("" when nothing)."""
    best = w["ranking"][0]
    out = []
    for t in w.get("pair_tests", []):
        if (t["significant"] and not t["material"] and not t.get("confounds")
                and set(t["single"]) == set(best["effects"])):
            extra = "+".join(e for e in t["pair"] if e not in t["single"])
            out.append(f"{extra} on top would close a further {t['gain_explained']:.2%} of the held-out gap (lower "
                       f"bound {t['gain_lower']:.2%}): below the {cfg.pair_material:.0%} materiality rule for a second "
                       f"effect, so not named (a share this small cannot be told from the model-form difference the "
                       f"simulator's settings leave)")
        trade = t.get("trade")
        if (trade and trade["is_trade"] and t["significant"] and t["material"]
                and set(t["single"]) == set(best["effects"])):
            out.append(f"not named: {'+'.join(t['pair'])}, which moves {trade['effect']} from "
                       f"{_num(trade['single_value'])} to {_num(trade['pair_value'])} and closes a further "
                       f"{t['gain_explained']:.2%} of the held-out gap: with {trade['effect']} held at "
                       f"{_num(trade['single_value'])}, {trade['second']} closes {trade['gain_explained']:+.2%} (lower "
                       f"bound {trade['gain_lower']:+.2%}), short of the pair rule (significant, at least "
                       f"{cfg.pair_min:.0%} of what the single leaves and {t['material_min']:.2%} of the gap): "
                       f"{trade['second']} stands in for a step of {trade['effect']}, not a second effect")
    for t in w.get("nuisance_tests", []):
        if t["admitted"] and t["effect"] in best["effects"]:
            out.append(t["summary"])
        elif not t["admitted"]:
            out.append(f"not named: {'+'.join(t['hypothesis'])} ({t['summary']}: read as the simulator's contact "
                       f"model being off, not as a physical effect)")
    return "".join(f"; {c}" for c in out)


def significant(w: dict[str, Any], cfg: DiagnoseConfig) -> bool:
    """The verdict's first rule: the best hypothesis beats the nominal model on cross-fitted
    held-out data, or the linear probe explains more than ``cfg.significant`` of the residual."""
    return bool(w["detection"]["significant"] or w["probe_explained_nominal"] > cfg.significant)


def verdict(w: dict[str, Any], cfg: DiagnoseConfig) -> dict[str, Any]:
    """The answer to "which": ``no significant gap``, ``explained`` (by the best hypothesis, with
    ``confident`` True/False) or ``unexplained by the library``. The reason names the rule that
    made the call and its numbers.

    Rules, in order:

    1. significant gap: the best hypothesis beats the nominal model on cross-fitted held-out data
       in a one-sided sign-flip test of block improvements (``w["detection"]``, level ``alpha`` /
       hypotheses), or the linear probe explains more than ``cfg.significant`` of the held-out
       residual; otherwise "no significant gap";
    2. "explained" needs both: the best closes at least ``cfg.attribute_min`` of the held-out gap
       above the noise floor -- or, with ``cfg.attribute_interval``, less, but the upper end of the
       explained fraction's bootstrap interval reaches that rule (then never confident: the logs
       cannot tell the share from the rule's edge, and "unexplained" would claim what they do not
       show) -- and the linear probe finds at most ``cfg.structure_max`` of that gap still
       systematic after it; otherwise "unexplained by the library", naming the rule(s) that
       failed;
    3. an "explained" call is confident when the explained fraction's lower bootstrap bound clears
       the attribute rule, the best beats the runner-up in ``cfg.confident_p`` of resamples, no
       other effect ties with it, the fit leaves no structure hint and, for a single, no second
       effect fitted on top of it could be material (the upper bound of its gain stays below the
       pair rule's materiality bar) and no significant second effect moves its estimate outside its
       own interval (a contact effect that does only qualifies the value: it may stand for the
       simulator's contact model) and, for a single, its value fitted where each joint moves slowest
       and where it moves fastest agrees (:mod:`stride_jax.gap.form`), and, for a pair, its second
       effect is material (a pair named for a confounder below the bar is not confident), and its
       value does not depend on the simulator's settings (where the calibration was checked again
       under it and replaced, :func:`settings_shift`); otherwise the reason names the conditions
       that failed.

    Every verdict lists the hypotheses the held-out data cannot tell apart from the best
    (``indistinguishable_from``). Which hypothesis is the best is the pair and nuisance rules'
    (:mod:`stride_jax.gap.admit`); the reason says what they set aside."""
    best = w["ranking"][0]
    det = w["detection"]
    name = "+".join(best["effects"])
    ties = _ties(w, cfg)
    tie_note = f"; indistinguishable on these logs from {', '.join(ties)}" if ties else ""
    flip = (f"sign-flip p = {det['p_value']:.3g}" + (f" (its floor; normal approximation {det['p_normal']:.2g})"
                                                      if det["p_value"] <= det.get("p_floor", 0) * 1.0001 else "")
            + f", needs < {det['level']:.3g} = {cfg.alpha:g} / {det['hypotheses']} hypotheses")
    probe = f"linear probe explains {w['probe_explained_nominal']:.1%} of the held-out residual (needs > {cfg.significant:.0%})"
    if not significant(w, cfg):
        return {"verdict": "no significant gap", "effects": [], "confident": False, "indistinguishable_from": ties,
                "rule": "detection",
                "reason": f"no significant gap: the best hypothesis ({name}) does not beat the nominal model on "
                          f"cross-fitted held-out data ({flip}; it explains {det['explained_crossfit']:.2%} cross-fitted, "
                          f"{best['explained']:.1%} held out) and the {probe}" + tie_note}
    why = (f"the gap is significant ({flip})" if det["significant"]
           else f"the gap is significant by the probe only ({probe}; {flip} fails)")
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
    closes = (f"the best hypothesis ({name}) closes {best['explained_above_floor']:.1%} of the held-out gap above "
              f"the noise floor ({best['explained']:.1%} of the whole gap)")
    left = f"the linear probe finds {w['structure_left']:.1%} of the gap above the floor still systematic after it"
    failed = []
    # the rule read on the whole gap, where the bootstrap interval lives: attribute_min of the gap
    # above the floor is ci_min of the whole gap
    ci_min = cfg.attribute_min * (1 - w["noise_floor"] / max(w["gap_ms"], 1e-300))
    under = best["explained_above_floor"] < cfg.attribute_min
    # under the rule, but the interval reaches it: named, never confidently (unless structure is left)
    edge = under and cfg.attribute_interval and best["explained"] > 0 and best["explained_ci"][1] >= ci_min
    short = under and not edge  # the 50% rule decides
    if short:
        failed.append(f"{closes}, below the {cfg.attribute_min:.0%} rule"
                      + (f" (its upper bound {best['explained_ci'][1]:.1%} of the whole gap stays below the rule's "
                         f"{ci_min:.1%})" if cfg.attribute_interval and best["explained"] > 0 else "")
                      + (" (it predicts held-out data worse than the nominal model)" if best["explained"] < 0 else ""))
    if w["structure_left"] > cfg.structure_max:
        if edge:
            failed.append(f"{closes}, under the {cfg.attribute_min:.0%} rule (its interval reaches it)")
        failed.append(f"{left}, above the {cfg.structure_max:.0%} rule")
    bounds = bound_note(best) + admission_note(w, cfg)
    if failed:
        return {"verdict": "unexplained by the library", "effects": best["effects"], "confident": False,
                "indistinguishable_from": ties, "rule": "attribute_min" if short else "structure_max",
                "reason": f"unexplained by the library: {'; and '.join(failed)}; {why}" + bounds + hint + tie_note}
    shortfalls, value_notes = [], []
    if edge:
        shortfalls.append(f"it closes {best['explained_above_floor']:.1%} of the gap above the floor, under the "
                          f"{cfg.attribute_min:.0%} rule, but the explained fraction's bootstrap interval "
                          f"[{best['explained_ci'][0]:.1%}, {best['explained_ci'][1]:.1%}] of the whole gap holds the "
                          f"rule's {ci_min:.1%}: these logs cannot tell it from the rule's edge")
    elif best["explained_ci"][0] < ci_min:
        shortfalls.append(f"the explained fraction's lower bound {best['explained_ci'][0]:.1%} is below "
                          f"{ci_min:.1%} (the {cfg.attribute_min:.0%} rule less the noise floor)")
    if best["p_beats_next"] < cfg.confident_p:
        shortfalls.append(f"it beats the runner-up in {best['p_beats_next']:.0%} of resamples (needs "
                          f"{cfg.confident_p:.0%})")
    if ties:
        shortfalls.append("other effects tie with it")
    t = best.get("vs_best_single")
    if len(best["effects"]) == 2 and t and t.get("confounds") and not t["material"]:
        extra = "+".join(e for e in t["pair"] if e not in t["single"])
        shifts = "; ".join(f"{_entry(m, best['params'])} {_num(m['single'])} alone -> {_num(m['in_pair'])} beside "
                           f"it, interval {_num(m['lo'])} to {_num(m['hi'])}" for m in t["moves"])
        single = "+".join(t["single"])
        shortfalls.append(f"{extra} on top closes a further {t['gain_explained']:.2%} of the held-out gap, below the "
                          f"{t['material_min']:.2%} materiality bar: it is named as a confounder, not for its share: "
                          f"fitted beside it, {single}'s estimate moves by {t['change_in_estimate']:.0%} of its "
                          f"departure from nominal and out of its own interval ({shifts}; the change-in-estimate rule "
                          f"asks at least {cfg.pair_confounds:.0%}), so {single} alone would misstate its value")
    for t in w.get("pair_tests", []):
        if (len(best["effects"]) == 1 and set(t["single"]) == set(best["effects"]) and not t["preferred"]
                and t.get("material_possible")):
            extra = "+".join(e for e in t["pair"] if e not in t["single"])
            g = t.get("trade") or t  # a trade: the second effect's gain with the integer held at the single's
            shortfalls.append(f"a material second effect cannot be ruled out: {extra} on top closes "
                              f"{g['gain_explained']:+.2%} of the held-out gap, up to {g['gain_upper']:.2%} "
                              f"({1 - cfg.alpha:.0%} bootstrap quantile), which reaches the "
                              f"{t['material_min']:.2%} materiality bar for naming a second effect")
        if (len(best["effects"]) == 1 and set(t["single"]) == set(best["effects"]) and t["significant"]
                and t.get("moves")):
            extra = [e for e in t["pair"] if e not in t["single"]]
            shifts = ", ".join(f"{_entry(m, best['params'])} {_num(m['single'])} -> {_num(m['in_pair'])} (interval "
                               f"{_num(m['lo'])} to {_num(m['hi'])})" for m in t["moves"])
            if all(e in nominal.OVERLAPS for e in extra):
                # a contact effect beside it may stand for the model-form difference the calibration
                # left (the pair rule's surrogates): the value is uncertain, not the effect named
                value_notes.append(f"its value moves with the simulator's contact model: with {'+'.join(extra)} "
                                   f"fitted beside it (a significant {t['gain_explained']:+.2%} of the held-out gap) "
                                   f"{shifts}; the interval holds the noise, not the contact model's uncertainty")
            else:
                shortfalls.append(f"its estimate depends on a second effect: with {'+'.join(extra)} fitted beside it "
                                  f"(a significant {t['gain_explained']:+.2%} of the held-out gap) it moves outside "
                                  f"its own interval: {shifts}")
    fc = w.get("form_check")
    if fc and fc["differs"] and fc["effect"] in best["effects"]:
        shortfalls.append(form.note(fc))
    moved = settings_shift(best, w.get("calibration_shift"), cfg.form_tol)
    if moved:
        shortfalls.append(f"its value depends on the simulator's settings: fitted on the first calibration's settings "
                          f"({'; '.join(w['calibration_shift']['first_settings']) or 'the nominal model'}) and on "
                          f"those fitted again with it held fixed, which predict the held-out split better, it moves "
                          f"outside its interval and by more than {cfg.form_tol:.0%} of its departure from nominal: "
                          + "; ".join(moved))
    if hint:
        shortfalls.append("the fit leaves structure (below)")
    confident = not shortfalls
    return {"verdict": "explained", "effects": best["effects"], "confident": confident,
            "indistinguishable_from": ties, "rule": "attribute_min",
            "reason": f"explained: {closes}, "
                      + (f"within reach of the {cfg.attribute_min:.0%} rule (below)" if edge
                         else f"at least the {cfg.attribute_min:.0%} rule")
                      + f", and {left} (at most "
                      f"{cfg.structure_max:.0%}); {why}; "
                      + (f"confident: it beats the runner-up in {best['p_beats_next']:.0%} of resamples" if confident
                         else "not confident: " + "; ".join(shortfalls))
                      + "".join(f"; {n}" for n in value_notes) + pair_note + bounds + hint + tie_note}


def settings_shift(best: dict[str, Any], shift: dict[str, Any] | None, tol: float) -> list[str]:
    """The entries of the best hypothesis whose value on the first settings (``shift["before"]``)
    lies outside its interval on the re-checked ones (:func:`stride_jax.gap.calibrate.recheck`),
    where it also moved by more than ``tol`` of its departure from nominal -- the pair rule's two
    measures (:func:`stride_jax.gap.admit.moves`, :func:`~stride_jax.gap.admit.change_in_estimate`);
    one line each, empty where none or no recheck was adopted. Both, as the form check's: intervals
    hold the noise, not the model-form bias, so intervals alone would flag most shifts."""
    before = {"params": (shift or {}).get("before") or {}}
    if not before["params"] or admit.change_in_estimate(best, before) <= tol:
        return []
    return [f"{_entry(m, best['params'])} {_num(m['in_pair'])} -> {_num(m['single'])} (interval {_num(m['lo'])} "
            f"to {_num(m['hi'])})" for m in admit.moves(best, before)]


def _entry(m: dict, params: dict) -> str:
    """A moved entry's name (:func:`stride_jax.gap.admit.moves`): the parameter, with its index
    where the effect has several (``com_offset[0]``)."""
    return m["param"] + (f"[{m['index']}]" if len(params[m["param"]]) > 1 else "")


def _num(x) -> str:
    return f"{float(x):.4g}"


def _at_bound(f: fit.Fit) -> dict[str, list[bool]]:
    return {n: [bool(b) for b in np.atleast_1d((f.at_bound or {}).get(n, np.zeros(effects.ALL[n].size, bool)))]
            for n in f.names}


def _jsonable(d: dict) -> dict:
    return {k: np.asarray(v, float).round(6).tolist() for k, v in d.items()}


def _fmt(params: dict) -> str:
    return ", ".join(f"{k}={np.array2string(np.asarray(v), precision=4)}" for k, v in params.items())
