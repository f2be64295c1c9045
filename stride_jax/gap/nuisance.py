"""Effects that overlap the simulator's own settings, and the null they must beat.

Two library effects act through the contact model that the calibration
(:mod:`stride_jax.gap.calibrate`) fits as nuisance settings: ``contact_softness`` *is* the solref
time constant, and ``ground_friction`` scales the sliding friction, whose effect on the feet the
friction cone, impratio and the contact impedance also shape. On top of a calibrated simulator whose
contact model still differs from the robot's in ways its settings cannot represent (every real
robot's does), such an effect can take up part of that model-form difference, and the held-out gain
it buys is "significant" on clean logs: the leftover model-form error is systematic, so it carries
over to held-out trajectories like an effect would.

The null for "the ground is softer" or "the ground is more slippery" is therefore "the contact model
is a bit off": the same hypothesis without the effect, with the continuous contact settings fitted
again on the training split (its other effects held fixed at their fitted values;
:class:`Null`). The effect is admitted only if the hypothesis beats that null on the held-out split
by the pair rule's measures (:func:`stride_jax.gap.admit.nuisance_test`). Where an effect has an
exact settings equivalent (``contact_softness`` = a factor on the solref time constant), the
null's search starts from the settings with the effect folded in, so the null contains the
hypothesis and can only match or beat it on the training split: such an effect is named only where
re-fitting the settings cannot reach what it does.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any

import numpy as np

from stride_jax.gap import baseline, calibrate, fit, nominal
from stride_jax.gap.nominal import OVERLAPS, Settings, fold_into
from stride_jax.sim.model import SimModel


class Null:
    """The null of an overlapping effect: the continuous contact settings re-fitted from the
    calibrated ``settings`` on the training split (every :func:`stride_jax.gap.calibrate.stride`-th replay, at most
    ``cfg.max_nfev`` least-squares evaluations per setting), with other effects held fixed on top.

    ``null(held, fold)`` returns ``(r, record)``: the scaled ``k``-step residual ``[M, nv]`` of the
    re-fitted model on the held-out split, with ``held`` (name -> parameters) on top; ``fold``
    (overlapping effect -> parameters) starts the search with those effects turned into their
    settings equivalent. Calls with the same arguments are cached."""

    def __init__(self, sm: SimModel, settings: Settings, train: fit.Data, test: fit.Data, scale: np.ndarray,
                 cfg: calibrate.CalibrateConfig, names: list[str]):
        self.sm, self.settings, self.test, self.scale, self.cfg, self.names = sm, settings, test, scale, cfg, names
        self.sub = calibrate._sub(train, calibrate.stride(cfg, len(train.start)))
        self._cache: dict[tuple, tuple[np.ndarray, dict]] = {}

    def start(self, fold: dict) -> Settings:
        """The calibrated settings with the effects of ``fold`` turned into their settings equivalent."""
        return fold_into(self.settings, fold, self.names)

    def __call__(self, held: dict, fold: dict | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        held = {n: np.atleast_1d(np.asarray(v, float)) for n, v in held.items()}
        fold = {n: np.atleast_1d(np.asarray(v, float)) for n, v in (fold or {}).items()}
        key = (tuple(sorted((n, tuple(v)) for n, v in held.items())), tuple(sorted((n, tuple(v)) for n, v in fold.items())))
        if key not in self._cache:
            t0 = time.time()
            evals = {"n": 0}
            start = self.start(fold)
            s, loss, _ = calibrate.fit_continuous(self.sm, start, self.sub, self.scale, self.names, self.cfg.max_nfev,
                                                  held, evals=evals)
            train_loss = lambda s_: float((baseline.residual(nominal.apply(self.sm, s_), self.sub, self.scale, held)
                                           ** 2).sum())
            s, loss = calibrate.parsimony(s, loss, self.names, train_loss, self.cfg.min_gain)
            r = baseline.residual(nominal.apply(self.sm, s), self.test, self.scale, held)
            rec = {"_settings": s, "held_fixed": {n: v.tolist() for n, v in held.items()},
                   "folded": {n: v.tolist() for n, v in fold.items() if OVERLAPS.get(n) in self.names},
                   "settings": {n: getattr(s, n) for n in self.names},
                   "refit": nominal.summary(s, self.sm),
                   "train_loss": loss, "evaluations": evals["n"], "seconds": time.time() - t0}
            self._cache[key] = (r, rec)
        return self._cache[key]


def make(sm: SimModel, settings: Settings, train: fit.Data, test: fit.Data, scale: np.ndarray,
         cfg: calibrate.CalibrateConfig) -> Null | None:
    """The :class:`Null` of the nominal model ``sm`` calibrated to ``settings`` (the nominal
    settings where calibration was not kept), or None where calibration is off or fits no
    continuous contact setting (nothing collides, or none is listed in ``cfg.continuous``)."""
    names = calibrate._names(cfg.continuous)
    if cfg.mode != "fit" or not names or nominal.describe(sm)["colliding_geoms"] == 0:
        return None
    return Null(sm, settings, train, test, scale, cfg, names)


def refit_baseline(w: dict[str, Any], cal) -> Settings | None:
    """The contact settings to score the effects on again, or None: where the nuisance rule set aside
    the hypothesis that leads the ranking (an overlapping effect re-read as the contact model) and
    its re-fit (:class:`Null`, with the hypothesis's other effects held fixed) predicts the held-out
    split better than the hypothesis named in its place, the calibration missed part of the contact
    model: the re-fitted settings, unless they are the calibrated ones."""
    tests = [t for t in w.get("nuisance_tests", []) if not t["admitted"]]
    if not tests:
        return None
    t = tests[0]
    s = t["_settings"]
    if s == cal.settings or t["null_explained"] <= w["ranking"][0]["explained"]:
        return None
    return s


def adopt(sm: SimModel, cal, settings: Settings, test: fit.Data, scale: np.ndarray, why: str):
    """``cal`` (a :class:`stride_jax.gap.calibrate.Calibration` of the nominal ``sm``) replaced by the
    re-fitted ``settings``: the new baseline, its held-out gap and sign-flip p against the nominal
    model, and the reason (``why``) in the record under ``refit``."""
    s = calibrate._neutral(settings, nominal.describe(sm))
    base = nominal.apply(sm, s)
    r_nom, r_cal = baseline.residual(sm, test, scale), baseline.residual(base, test, scale)
    g_nom, g_cal = fit.gap(r_nom), fit.gap(r_cal)
    rec = cal.record | {
        "applied": True, "settings": {f.name: getattr(s, f.name) for f in dataclasses.fields(s)},
        "changed": nominal.summary(s, sm), "proposed": nominal.summary(s, sm),
        "heldout_gap_calibrated": g_cal, "heldout_gap_proposed": g_cal, "shrink": 1 - g_cal / max(g_nom, 1e-300),
        "p_value": calibrate.paired_p(r_nom, r_cal, test, 10, 11),
        "refit": {"why": why, "first": cal.record.get("changed", [])}}
    return calibrate.Calibration(model=base, settings=s, record=rec)
