"""The baseline that physical effects are scored against, and what it closes: the simulator's
settings as :mod:`stride_jax.gap.calibrate` fitted them, rebuilt from a diagnosis's record, the
``k``-step residual and gap of a model with library effects on top, the held-out gaps of the
nominal model, the baseline and the final hypothesis, and the calibration's clause in the
verdict.

The search for the settings is :mod:`stride_jax.gap.calibrate`'s; this module only scores and
describes its outcome (the diagnosis, its report and the benchmarks read it).
"""

from __future__ import annotations

import numpy as np

from stride_jax.gap import effects, fit, nominal
from stride_jax.gap.nominal import Settings
from stride_jax.sim.model import SimModel


def residual(model: SimModel, data: fit.Data, scale: np.ndarray, applied: dict | None = None) -> np.ndarray:
    """``[M, nv]`` scaled k-step residual of ``model`` with the library effects ``applied``
    (name -> parameters; none by default) on top."""
    plan = effects.build(model, {n: np.atleast_1d(np.asarray(v, float)) for n, v in (applied or {}).items()})
    return fit.residual(model, plan, data, scale)


def gap_of(model: SimModel, trajs: list, scale: np.ndarray, k: int = 1, applied: dict | None = None) -> float:
    """The gap (:func:`stride_jax.gap.fit.gap`) of ``model`` with the library effects ``applied``
    (name -> parameters) on trajectories ``trajs`` (``k``-step replays)."""
    data = fit.make_data(trajs, k)
    plan = effects.build(model, {n: np.atleast_1d(np.asarray(v, float)) for n, v in (applied or {}).items()})
    return fit.gap(fit.residual(model, plan, data, scale))


def baseline_of(sm: SimModel, record: dict | None) -> SimModel:
    """The baseline a diagnosis scored effects against, rebuilt from its ``calibration`` record."""
    if not record or not record.get("applied"):
        return sm
    return nominal.apply(sm, Settings(**record["settings"]))


def shrinks(sm: SimModel, base: SimModel, plan_best: effects.Plan, test: fit.Data, scale: np.ndarray
            ) -> dict[str, float]:
    """Held-out one-step gaps of the nominal model, the calibrated baseline and the best hypothesis
    on top of it; the shrink of the final model against the nominal model and against the
    baseline, and the calibration's own share."""
    g_nom = fit.gap(residual(sm, test, scale))
    g_base = g_nom if base is sm else fit.gap(residual(base, test, scale))
    g_best = fit.gap(fit.residual(base, plan_best, test, scale))
    tiny = 1e-300
    return {"gap_nominal": g_nom, "gap_baseline": g_base, "gap_final": g_best,
            "shrink_vs_nominal": 1 - g_best / max(g_nom, tiny),
            "shrink_vs_baseline": 1 - g_best / max(g_base, tiny),
            "calibration_shrink": 1 - g_base / max(g_nom, tiny)}


def sentence(record: dict | None) -> str:
    """The calibration in one clause for the verdict, e.g. "the simulator's settings are off:
    cone: elliptic -> pyramidal; time step: 2 ms -> 4 ms (calibrated first: 93.1% of the
    held-out gap)"; empty when calibration was off."""
    if not record or record.get("mode") == "off":
        return ""
    if not record["applied"]:
        return ("the simulator's settings match the nominal model (calibration of time step, integrator, cone, "
                "contacts and contact parameters did not lower the held-out gap)")
    refit = (f"; the contact settings were fitted again after the effects, as {record['refit']['why']}"
             if record.get("refit") else "")
    held = list(record.get("effects_held_fixed") or {})
    share = (f"they close {record['shrink']:.1%} of the held-out {record['k']}-step gap, sign-flip p = "
             f"{record['p_value']:.2g}")
    recheck = record.get("recheck") or {}
    if recheck.get("adopted"):  # fitted again under the best hypothesis (calibrate.recheck)
        return (f"the simulator's settings are off: {'; '.join(record['changed'])} (fitted again with the best "
                f"hypothesis, {', '.join(held)}, held fixed on top, which with them leaves "
                f"{recheck['heldout_gap'] / max(recheck['heldout_gap_before'], 1e-300):.1%} of the held-out "
                f"gap it left on the first calibration's settings; on their own {share}{refit})")
    if held and record["shrink"] <= 0:  # kept because they lower the gap with the held effect on top
        share = (f"fitted with {', '.join(held)} held fixed on top, with which they lower the held-out gap; "
                 f"without it {share}")
    return f"the simulator's settings are off: {'; '.join(record['changed'])} (calibrated first: {share}{refit})"
