"""Where in the data a residual lives: names of the dofs, contact phases of the feet, state bins.

Shared by the decomposition of the nominal residual (:func:`stride_jax.gap.localise.where`) and
by the concentration of the STRIDE residual fitted on top of the best hypothesis
(:mod:`stride_jax.gap.residual`), so that both speak of the same phases and the same bins.
"""

from __future__ import annotations

import mujoco
import numpy as np

from stride_jax.gap import fit
from stride_jax.sim.model import SimModel

PHASES = ("swing", "stance", "touchdown", "liftoff")


def rms(x, axis=None):
    """Root mean square (a float without ``axis``, an array with it)."""
    return float(np.sqrt(np.mean(x ** 2))) if axis is None else np.sqrt(np.mean(x ** 2, axis=axis))


def dof_names(sm: SimModel) -> list[str]:
    """``[nv]`` one name per velocity coordinate (``base_vx`` ... ``base_wz`` for a free joint)."""
    m = sm.mj
    out = []
    for j in range(m.njnt):
        if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE:
            out += ["base_vx", "base_vy", "base_vz", "base_wx", "base_wy", "base_wz"]
        else:
            out.append(m.joint(j).name)
    return out


def leg_dofs(sm: SimModel, foot: str) -> list[int]:
    """The dofs of a foot's leg (named ``<foot>_...``); all dofs if none are."""
    names = dof_names(sm)
    return [i for i, n in enumerate(names) if n.startswith(foot + "_")] or list(range(len(names)))


def noise_floor(r: np.ndarray, data: fit.Data) -> float:
    """Mean squared residual (summed over dofs) attributable to white velocity noise: the
    ``data``'s own when the noise level was given with the logs (:func:`noise_floor_of`);
    otherwise ``-2 x`` the lag-``k`` autocovariance within trajectories, clipped at zero per dof
    (the noise of the logged velocity at ``t + k`` enters residual ``t`` with a minus sign and
    residual ``t + k`` through its initial state). The second is a rough reading: the model
    error's own autocovariance mixes in (measured on the independent benchmark's noisy cases
    against their clean twins: 0.08-3.1 x what the noise adds, ``results/
    gap_noise_floor_check.md``)."""
    if data.noise_floor is not None:
        return data.noise_floor
    k = data.k
    same = data.traj[k:] == data.traj[:-k]
    if not same.any():
        return 0.0
    rc = r - r.mean(0)
    acov = (rc[k:][same] * rc[:-k][same]).mean(0)
    return float(np.maximum(-2 * acov, 0).sum())


def noise_floor_of(sm: SimModel, plan, data: fit.Data, scale: np.ndarray, std: np.ndarray,
                   draws: int = 2, seed: int = 0) -> float:
    """The gap (:func:`stride_jax.gap.fit.gap`) that white noise of standard deviation ``std [nv]``
    on the logged velocities adds to ``data``'s ``k``-step replays under ``plan``: its variance
    in each replay's target (``sum (std / (k dt scale))^2``) plus what it does through each
    replay's start, measured by replaying again from starts with that much more noise (``draws``
    times; the increase of the mean squared residual is what the noise already in the logs adds
    there, in expectation). Replays that diverge only when perturbed are left out of the
    increase."""
    unit = data.k * sm.robot.ctrl_dt * scale
    target = float(((np.asarray(std, float) / unit) ** 2).sum())
    r0 = fit.residual(sm, plan, data, scale)
    ok0 = (np.abs(r0) < 1e3).all(1)
    rng = np.random.default_rng(seed)
    rise = []
    for _ in range(draws):
        qd = data.qd + np.asarray(std, float) * rng.standard_normal(data.qd.shape)
        r1 = fit.residual(sm, plan, data._replace(qd=qd), scale)  # the targets stay as logged
        ok = ok0 & (np.abs(r1) < 1e3).all(1)
        if ok.any():
            rise.append(float((r1[ok] ** 2).sum(1).mean() - (r0[ok] ** 2).sum(1).mean()))
    return target + max(float(np.mean(rise)) if rise else 0.0, 0.0)


def foot_phases(sm: SimModel, q: np.ndarray, bounds: np.ndarray, margin: float = 0.015
                ) -> np.ndarray:
    """``[N, nfeet]`` phase index (:data:`PHASES`) of each foot from kinematics alone: stance while
    the foot site is within ``margin`` m of its lowest height (5th percentile) in the log."""
    if sm.nfeet == 0:
        return np.zeros((len(q), 0), int)
    m = sm.mj
    d = mujoco.MjData(m)
    h = np.empty((len(q), sm.nfeet))
    for i, qi in enumerate(q):
        d.qpos[:] = qi
        mujoco.mj_kinematics(m, d)
        h[i] = d.site_xpos[sm.foot_sites, 2]
    stance = h < np.percentile(h, 5, axis=0) + margin
    prev = stance.copy()
    for a, b in zip(bounds[:-1], bounds[1:]):
        prev[a + 1:b] = stance[a:b - 1]
    phase = np.where(stance, 1, 0)
    phase = np.where(stance & ~prev, 2, phase)
    return np.where(~stance & prev, 3, phase)


def sample_phases(sm: SimModel, data: fit.Data) -> np.ndarray:
    """``[M, nfeet]`` contact phase of each foot at each replayed sample of ``data``."""
    return foot_phases(sm, data.q, data.bounds)[fit.samples_before_next(data)]


def symmetric_bins(v: np.ndarray, bins: int) -> tuple[np.ndarray, np.ndarray]:
    """``bins`` equal bins over ``[-lim, lim]``, ``lim`` the 98th percentile of ``|v|`` (outliers
    fall into the outer bins). Returns ``(index [len(v)], centres [bins])``."""
    lim = np.quantile(np.abs(v), 0.98) + 1e-9
    edges = np.linspace(-lim, lim, bins + 1)
    k = np.clip(np.searchsorted(edges, v, side="right") - 1, 0, bins - 1)
    return k, (edges[:-1] + edges[1:]) / 2


def quantile_bins(x: np.ndarray, bins: int) -> tuple[np.ndarray, np.ndarray]:
    """At most ``bins`` bins of equal counts (ties merge edges). Returns ``(index [len(x)],
    edges [nbins + 1])``."""
    edges = np.unique(np.quantile(x, np.linspace(0, 1, bins + 1)))
    if len(edges) < 2:
        edges = np.array([edges[0], edges[0]])
    return np.clip(np.searchsorted(edges, x, side="right") - 1, 0, len(edges) - 2), edges


def base_speed(data: fit.Data) -> np.ndarray:
    """``[M]`` horizontal base speed (m/s) at each replayed sample (floating bases only)."""
    return np.linalg.norm(data.qd[fit.samples_before_next(data), :2], axis=1)
