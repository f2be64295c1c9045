"""Is the named effect's form right? Its value, fitted on the slowest and the fastest logs.

A physical parameter of the right form is one number whatever the robot does: joint damping is
the same at 1 and at 8 rad/s. An effect of another form that a library effect imitates is not: a
quadratic drag ``-c qd |qd|`` fitted as linear damping takes a damping that grows with speed
(measured on the independent Go1 benchmark: a planted quadratic drag named ``servo_damping``,
confidently, at 78% of the gap). :func:`check` refits the named single on the slowest and the
fastest third of the replay windows (by the RMS of the actuated joints' velocities where each
window starts) and compares the two estimates: they **differ** when their intervals do not overlap and
they are further apart than ``tol`` of the larger of their two departures from the nominal value
-- both, because under a model-form difference the intervals hold the noise and not the bias
(the pair rule measured a surrogate moving damping by 7%), so intervals alone would flag right
effects. ``tol`` (25%) is a stated convention, like the pair rule's 5% materiality. A differing
estimate makes the call not confident (:func:`stride_jax.gap.attribute.verdict`). Thirds, not
halves: the contrast in speed is what the check sees (a trotting Go1's windows span only ~1.5x in
RMS joint speed between its slowest and fastest thirds).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from stride_jax.gap import effects, fit
from stride_jax.sim.model import SimModel


def by_speed(sm: SimModel, data: fit.Data, share: float = 0.5) -> tuple[fit.Data, fit.Data, tuple[float, float]]:
    """``(slow, fast, (lower cut, upper cut))``: the replay windows of ``data`` whose start's RMS
    actuated joint speed is at most the ``share`` quantile / above the ``1 - share`` quantile
    (rad/s; ``share`` 0.5: the two halves)."""
    speed = np.sqrt(np.mean(data.qd[data.start][:, sm.act_dof] ** 2, axis=1))
    lo, hi = (float(np.quantile(speed, x)) for x in (share, 1 - share))
    pick = lambda m: data._replace(start=data.start[m], first=data.first[m], target=data.target[m],
                                   traj=data.traj[m])
    return pick(speed <= lo), pick(speed > hi), (lo, hi)


def check(sm: SimModel, train: fit.Data, scale: np.ndarray, row: dict[str, Any], cfg: fit.FitConfig,
          tol: float, share: float = 1 / 3, min_windows: int = 40) -> dict[str, Any] | None:
    """The named single ``row`` (a ranking row: ``effects``, ``params``) refitted on the slowest and
    the fastest ``share`` of ``train``'s windows (:func:`by_speed`): ``{"effect", "cuts", "share",
    "windows", "slow", "slow_lo", "slow_hi", "fast", ..., "differs", "entries"}`` (None for a pair,
    or when a part has fewer than ``min_windows`` windows)."""
    if len(row["effects"]) != 1:
        return None
    (name,) = row["effects"]
    slow, fast, cuts = by_speed(sm, train, share)
    if min(len(slow.start), len(fast.start)) < min_windows:
        return None
    start = {name: np.asarray(row["params"][name], float)}
    fits = [fit.fit(sm, half, scale, (name,), dataclasses.replace(cfg, profile=max(cfg.profile, 1)), start)
            for half in (slow, fast)]
    nominal = np.asarray(effects.ALL[name].nominal, float)
    a, b = (np.asarray(f.params[name], float) for f in fits)
    alo, ahi = (np.asarray(v[name], float) for v in (fits[0].lo, fits[0].hi))
    blo, bhi = (np.asarray(v[name], float) for v in (fits[1].lo, fits[1].hi))
    apart = (alo > bhi) | (blo > ahi)
    size = np.maximum(np.abs(a - nominal), np.abs(b - nominal))
    far = np.abs(a - b) > tol * np.maximum(size, 1e-12)
    entries = [i for i in range(len(a)) if apart[i] and far[i]]
    return {"effect": name, "cuts": list(cuts), "share": share, "windows": [len(slow.start), len(fast.start)],
            "slow": a.tolist(), "slow_lo": alo.tolist(), "slow_hi": ahi.tolist(),
            "fast": b.tolist(), "fast_lo": blo.tolist(), "fast_hi": bhi.tolist(), "tol": tol,
            "differs": bool(entries), "entries": entries}


def note(c: dict[str, Any]) -> str:
    """The verdict's clause for a differing check."""
    labels = effects.ALL[c["effect"]].labels
    parts = [(f"{labels[i]}: " if len(c["slow"]) > 1 else "")
             + f"{c['slow'][i]:.4g} [{c['slow_lo'][i]:.4g}, {c['slow_hi'][i]:.4g}] on the slower windows, "
             f"{c['fast'][i]:.4g} [{c['fast_lo'][i]:.4g}, {c['fast_hi'][i]:.4g}] on the faster" for i in c["entries"]]
    return (f"its value changes with joint speed (the slowest and the fastest {c['share']:.0%} of the windows, "
            f"below {c['cuts'][0]:.2f} and above {c['cuts'][1]:.2f} rad/s RMS): "
            + "; ".join(parts) + f" -- apart beyond both intervals and by more than {c['tol']:.0%}: an effect "
            "of this form does not fit both, so another (e.g. a drag nonlinear in speed) may be at work")
