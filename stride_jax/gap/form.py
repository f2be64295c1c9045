"""Is the named effect's form right? Its value, fitted where each joint moves slowest and fastest.

A physical parameter of the right form is one number whatever the robot does: joint damping is
the same at 1 and at 8 rad/s. An effect of another form that a library effect imitates is not: a
quadratic drag ``-c qd |qd|`` fitted as linear damping takes a damping that grows with speed
(measured on the independent Go1 benchmark: a planted quadratic drag named ``servo_damping``,
confidently, at 78% of the gap). :func:`check` refits the named single twice on the same replay
windows, once on the residual entries where each joint moves slowest and once where it moves
fastest (:func:`by_joint_speed`: each actuated joint's slowest and fastest ``share`` of its own
speeds over the windows; the unactuated dofs, a floating base's, by the windows' RMS over all
actuated joints), and compares the two estimates: they **differ** when their intervals do not
overlap and they are further apart than ``tol`` of the larger of their two departures from the
nominal value -- both, because under a model-form difference the intervals hold the noise and not
the bias (the pair rule measured a surrogate moving damping by 7%), so intervals alone would flag
right effects. ``tol`` (25%) is a stated convention, like the pair rule's 5% materiality. A
differing estimate makes the call not confident (:func:`stride_jax.gap.attribute.verdict`).
The intervals are profiled only where the two estimates are that far apart: closer, they cannot
differ whatever their intervals (on the 12 x 8 s Go1 logs of ``results/gap_speed.md`` the two
profiles were a third of the check's replays).

Per joint, not per window: a trotting Go1's windows span only ~1.5x in RMS joint speed between
their slowest and fastest thirds, and a split of whole windows left the planted drag's two
damping values 21% apart with touching intervals (session 22). Each joint alone spans from
near rest to its peak speed within every gait cycle.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from stride_jax.gap import effects, fit
from stride_jax.sim.model import SimModel


def by_joint_speed(sm: SimModel, data: fit.Data, share: float = 1 / 3
                   ) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """``(slow [M, nv], fast [M, nv], (lower cuts, upper cuts))``: 0/1 masks of the residual's
    entries for the slowest and the fastest ``share`` of each actuated joint's own speeds over its
    replay windows (the RMS of the logged ``qd`` from the window's start to its target, ``k``
    periods later: a trotting leg's joint speed changes by several rad/s within a 60 ms window,
    so the start alone says little); every other dof (a floating base's) goes by the window's RMS
    over all actuated joints. The cuts ``[nv]`` are in those speeds (rad/s)."""
    rows = data.start[:, None] + np.arange(data.k + 1)[None, :]          # [M, k + 1], inside the trajectory
    qd = data.qd[rows][:, :, sm.act_dof]                                  # [M, k + 1, nu]
    joint = np.sqrt(np.mean(qd ** 2, axis=1))                             # [M, nu]
    speed = np.repeat(np.sqrt(np.mean(joint ** 2, axis=1))[:, None], sm.mj.nv, axis=1)
    speed[:, sm.act_dof] = joint
    lo, hi = np.quantile(speed, share, axis=0), np.quantile(speed, 1 - share, axis=0)
    return (speed <= lo).astype(float), (speed > hi).astype(float), (lo, hi)


def check(sm: SimModel, train: fit.Data, scale: np.ndarray, row: dict[str, Any], cfg: fit.FitConfig,
          tol: float, share: float = 1 / 3, min_windows: int = 40, cache: dict | None = None
          ) -> dict[str, Any] | None:
    """The named single ``row`` (a ranking row: ``effects``, ``params``) refitted on the entries of
    ``train``'s residual where each joint moves slowest and fastest (:func:`by_joint_speed`):
    ``{"effect", "cuts", "share", "windows", "slow", "slow_lo", "slow_hi", "fast", ..., "intervals",
    "differs", "entries"}`` (``cuts``: the median over the actuated joints of their lower and upper cuts;
    ``intervals``: whether the estimates were far enough apart for their intervals to decide, the
    ``*_lo``/``*_hi`` None otherwise;
    ``windows``: replay windows; None for a pair, or with fewer than ``min_windows`` windows in a
    share). ``cache``: replays of the effect on ``train`` made already (the named fit's: its grid
    is most of this check's, :func:`stride_jax.gap.fit.Objective`)."""
    if len(row["effects"]) != 1:
        return None
    (name,) = row["effects"]
    if share * len(train.start) < min_windows:
        return None
    slow, fast, (lo, hi) = by_joint_speed(sm, train, share)
    start = {name: np.asarray(row["params"][name], float)}
    shared = {} if cache is None else cache  # the two fits differ in their mask only: one grid's replays
    cfg = dataclasses.replace(cfg, profile=max(cfg.profile, 1))
    masks = (slow, fast)
    fits = [fit.fit(sm, train, scale, (name,), cfg, start, interval=False, mask=m, cache=shared) for m in masks]
    nominal = np.asarray(effects.ALL[name].nominal, float)
    a, b = (np.asarray(f.params[name], float) for f in fits)
    size = np.maximum(np.abs(a - nominal), np.abs(b - nominal))
    far = np.abs(a - b) > tol * np.maximum(size, 1e-12)
    act = sm.act_dof
    out = {"effect": name, "cuts": [float(np.median(lo[act])), float(np.median(hi[act]))], "share": share,
           "split": "per joint", "windows": int(len(train.start)), "slow": a.tolist(), "fast": b.tolist(),
           "tol": tol, "intervals": bool(far.any()), "slow_lo": None, "slow_hi": None, "fast_lo": None,
           "fast_hi": None, "differs": False, "entries": []}
    if not far.any():  # closer than tol: they agree whatever their intervals
        return out
    fits = [fit.with_interval(sm, train, scale, f, cfg, mask=m, cache=shared) for f, m in zip(fits, masks)]
    alo, ahi = (np.asarray(v[name], float) for v in (fits[0].lo, fits[0].hi))
    blo, bhi = (np.asarray(v[name], float) for v in (fits[1].lo, fits[1].hi))
    apart = (alo > bhi) | (blo > ahi)
    entries = [i for i in range(len(a)) if apart[i] and far[i]]
    return out | {"slow_lo": alo.tolist(), "slow_hi": ahi.tolist(), "fast_lo": blo.tolist(), "fast_hi": bhi.tolist(),
                  "differs": bool(entries), "entries": entries}


def note(c: dict[str, Any]) -> str:
    """The verdict's clause for a differing check."""
    labels = effects.ALL[c["effect"]].labels
    parts = [(f"{labels[i]}: " if len(c["slow"]) > 1 else "")
             + f"{c['slow'][i]:.4g} [{c['slow_lo'][i]:.4g}, {c['slow_hi'][i]:.4g}] where the joints move slower, "
             f"{c['fast'][i]:.4g} [{c['fast_lo'][i]:.4g}, {c['fast_hi'][i]:.4g}] where they move faster"
             for i in c["entries"]]
    return (f"its value changes with joint speed (where each joint moves slowest and fastest, the {c['share']:.0%} "
            f"of its samples below and above cuts of median {c['cuts'][0]:.2f} and {c['cuts'][1]:.2f} rad/s): "
            + "; ".join(parts) + f" -- apart beyond both intervals and by more than {c['tol']:.0%}: an effect "
            "of this form does not fit both, so another (e.g. a drag nonlinear in speed) may be at work")
