"""Where a fitted residual lives: its magnitude per dof, per contact phase of each foot, per
base-speed bin and per bin of each actuated joint's velocity and position (relative to its home
angle), beside the residual actually left there -- the phases and bins of
:func:`stride_jax.gap.localise.where`. Used on the STRIDE residual fitted on top of the best
hypothesis (:mod:`stride_jax.gap.residual`): a bin where the fit is small but the residual left
is not shows what the fit missed.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from stride_jax.gap import fit, regions
from stride_jax.sim.model import SimModel


def _cell(fitted: np.ndarray, left: np.ndarray, sel: np.ndarray, overall: float) -> dict[str, Any]:
    """RMS of the fitted correction and of the residual left over the samples ``sel``, and the
    fitted RMS relative to its overall RMS (> 1: concentrated here)."""
    if not sel.any():
        return {"count": 0, "rms": None, "left_rms": None, "ratio": None}
    rms = regions.rms(fitted[sel])
    return {"count": int(sel.sum()), "rms": rms, "left_rms": regions.rms(left[sel]),
            "ratio": rms / max(overall, 1e-300)}


def _joint_bins(values: np.ndarray, fitted: np.ndarray, left: np.ndarray, bins: int
                ) -> list[dict[str, Any]]:
    """Bins of one joint's velocity or position: count, RMS and signed mean of the joint's own
    fitted correction and of its residual left (rad/s^2 or m/s^2)."""
    k, centres = regions.symmetric_bins(values, bins)
    overall = regions.rms(fitted)
    out = []
    for i in range(bins):
        sel = k == i
        row = {"centre": float(centres[i])} | _cell(fitted, left, sel, overall)
        row["mean"] = float(fitted[sel].mean()) if sel.any() else None
        row["left_mean"] = float(left[sel].mean()) if sel.any() else None
        out.append(row)
    return out


def concentration(sm: SimModel, data: fit.Data, fitted: np.ndarray, left: np.ndarray,
                  force: np.ndarray, scale: np.ndarray, bins: int = 8) -> dict[str, Any]:
    """Where the fitted residual lives on the samples of ``data``.

    ``fitted [M, nv]``: the acceleration the residual adds to the simulator's (``M^-1 eps``,
    scaled); ``left [M, nv]``: what the best hypothesis leaves (logged minus simulated
    acceleration, scaled; a good fit matches it in sign and size); ``force [M, nv]``: the fitted
    generalised force ``eps``.
    Per dof: mean |force|, RMS of the correction (scaled) and its share of the total; per foot and
    contact phase and per base-speed bin: scaled RMS over all dofs (and over the leg's dofs);
    per bin of each actuated joint's velocity and position (from home): the joint's own
    correction in rad/s^2 (m/s^2). ``summary`` names the dof, the phase and the bins where it
    is largest."""
    names = regions.dof_names(sm)
    idx = fit.samples_before_next(data)
    ms = (fitted ** 2).mean(0)
    overall = regions.rms(fitted)
    out: dict[str, Any] = {"per_dof": {n: {"force_mean_abs": float(np.abs(force[:, i]).mean()),
                                           "rms_scaled": float(np.sqrt(ms[i])),
                                           "left_rms_scaled": float(regions.rms(left[:, i])),
                                           "share": float(ms[i] / max(ms.sum(), 1e-300))}
                                       for i, n in enumerate(names)},
                           "rms_scaled": overall, "left_rms_scaled": regions.rms(left)}
    phases = regions.sample_phases(sm, data)
    per_foot = {}
    for f, foot in enumerate(sm.robot.feet):
        leg = regions.leg_dofs(sm, foot.name)
        per_foot[foot.name] = {label: _cell(fitted, left, phases[:, f] == p, overall)
                               | {"rms_leg": regions.rms(fitted[phases[:, f] == p][:, leg])
                                  if (phases[:, f] == p).any() else None}
                               for p, label in enumerate(regions.PHASES)}
    out["per_foot_phase"] = per_foot
    if sm.robot.floating_base:
        k, edges = regions.quantile_bins(regions.base_speed(data), bins)
        out["base_speed_bins"] = [{"lo": float(edges[i]), "hi": float(edges[i + 1])}
                                  | _cell(fitted, left, k == i, overall)
                                  for i in range(len(edges) - 1) if (k == i).any()]
    raw_fit, raw_left = fitted * scale, left * scale
    q0 = np.asarray(sm.info.qpos0, np.float64)
    qadr = sm.mj.jnt_qposadr[sm.mj.actuator_trnid[:, 0]]
    out["joint_velocity_bins"] = {names[d]: _joint_bins(data.qd[idx, d], raw_fit[:, d], raw_left[:, d], bins)
                                  for d in sm.act_dof}
    out["joint_position_bins"] = {names[d]: _joint_bins(data.q[idx, a] - q0[a], raw_fit[:, d], raw_left[:, d], bins)
                                  for d, a in zip(sm.act_dof, qadr, strict=True)}
    out["summary"] = _summary(out)
    return out


def _peak(rows: list[dict], min_count: int) -> dict | None:
    rows = [r for r in rows if r["count"] >= min_count and r["rms"] is not None]
    return max(rows, key=lambda r: r["rms"], default=None)


def _summary(c: dict[str, Any], min_count: int = 10) -> dict[str, Any]:
    """The dof with the largest share; the foot phase, base-speed bin and joint bins with the
    largest RMS among those with at least ``min_count`` samples."""
    dof = max(c["per_dof"], key=lambda n: c["per_dof"][n]["share"])
    out: dict[str, Any] = {"dof": dof, "dof_share": c["per_dof"][dof]["share"]}
    phases = [dict(r, foot=f, phase=p) for f, rows in c["per_foot_phase"].items() for p, r in rows.items()]
    if (pk := _peak(phases, min_count)) is not None:
        out["phase"] = {"foot": pk["foot"], "phase": pk["phase"], "ratio": pk["ratio"]}
    if (pk := _peak(c.get("base_speed_bins", []), min_count)) is not None:
        out["base_speed"] = {"lo": pk["lo"], "hi": pk["hi"], "ratio": pk["ratio"]}
    for key in ("joint_velocity_bins", "joint_position_bins"):
        peaks = [dict(pk, joint=j) for j, rows in c[key].items() if (pk := _peak(rows, min_count))]
        if peaks:
            pk = max(peaks, key=lambda r: r["rms"])
            out[key.removesuffix("_bins")] = {"joint": pk["joint"], "centre": pk["centre"], "ratio": pk["ratio"]}
    return out
