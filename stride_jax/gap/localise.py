"""Where the gap lies (the diagnosis's first question), from the nominal model's replays of logs.

:func:`where` decomposes the one-step residual (logged minus predicted velocity change per
second, scaled per dof) per dof, per contact phase of each foot (estimated from foot heights:
logs carry no forces), per base-speed and per joint-velocity bin, and over time;
:func:`divergence` gives the open-loop rollout error of each dof against horizon.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from stride_jax.gap import effects, fit, logs, regions, sim
from stride_jax.gap.regions import PHASES, dof_names
from stride_jax.sim.model import SimModel

if TYPE_CHECKING:
    from stride_jax.gap.diagnose import DiagnoseConfig

_rms = regions.rms


def where(sm: SimModel, data: fit.Data, r: np.ndarray, scale: np.ndarray, cfg: DiagnoseConfig
          ) -> dict[str, Any]:
    """Decomposes the nominal one-step residual ``r [M, nv]`` (scaled) of ``data``."""
    names = dof_names(sm)
    idx = fit.samples_before_next(data)
    raw = r * scale  # rad/s^2 or m/s^2
    out: dict[str, Any] = {"dof_names": names,
                           "per_dof_rms": dict(zip(names, _rms(raw, 0).tolist(), strict=True)),
                           "per_dof_rms_scaled": dict(zip(names, _rms(r, 0).tolist(), strict=True)),
                           "scale": dict(zip(names, scale.tolist(), strict=True))}
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
    for dof in sm.act_dof:
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
            "final_rmse": dict(zip(names, np.sqrt((e[:, -1] ** 2).mean(0)).tolist(), strict=True)),
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
