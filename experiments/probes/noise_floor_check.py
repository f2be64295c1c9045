"""How well the gap tool's noise floor estimates what sensor noise adds to the gap.

On the independent benchmark's cases (``stride_jax.jobs.gap_bench_independent``, the default
preset) the noisy logs have clean twins: the same motion before the sensors. Replaying both
with the same model (the shipped nominal) over the same held-out ``k``-step windows, the
noise's actual share of the gap is ``gap(noisy) - gap(clean)``; the tool's estimate is
``stride_jax.gap.regions.noise_floor`` of the noisy residual (``-2 x`` the lag-``k``
autocovariance). Per dof, with ``sigma^2`` the logged velocity's noise variance (scaled as the
residual is) and ``J`` how much of an initial velocity error a ``k``-step replay keeps, the
noise adds ``sigma^2 (1 + J^2)`` while the autocovariance reads ``-J sigma^2`` plus the model
error's own autocovariance (positive where the model's error persists, which hides the noise's).
Printed beside the tool's estimate: ``2 sigma^2`` (``J = 1``) with the true ``sigma^2`` (from the
twins) and with the level the noisy logs show (``filters.noise_std``, second differences), and
per dof the larger of that ``sigma^2`` and the tool's ``-2 acov``; last, the floor the diagnosis
computes when the logs' header gives the sensors' noise levels (``velocity_noise``:
:func:`stride_jax.gap.regions.noise_floor_of`, session 44).

    python experiments/probes/noise_floor_check.py 0 1 2 ...   # case indices (0: the control)
"""
import dataclasses
import json
import sys

import numpy as np

from stride_jax.gap import diagnose, effects, filters, fit, regions
from stride_jax.jobs import gap_bench_independent as gbi


def acov_k(r: np.ndarray, data: fit.Data) -> np.ndarray:
    """``[nv]`` lag-``k`` autocovariance of the residual within trajectories."""
    k = data.k
    same = data.traj[k:] == data.traj[:-k]
    rc = r - r.mean(0)
    return (rc[k:][same] * rc[:-k][same]).mean(0)


def main(indices: list[int]) -> None:
    cfg = dataclasses.replace(gbi.PRESETS["default"], sensor_spec=True)  # the levels in the header
    dcfg = diagnose.PRESETS[cfg.diagnose]
    for index in indices:
        sm, noisy, clean, settings, form, spec = gbi.as_read(cfg, index, True)
        by = {t.name: t for t in clean}
        clean = [by[t.name] for t in noisy]
        pn, pc = diagnose.prepare(sm, noisy, dcfg, spec), diagnose.prepare(sm, clean, dcfg)
        assert pn.te_idx == pc.te_idx
        plan = effects.build(pn.sm, {})
        floor_from_spec = pn.test_k.noise_floor
        dn, dc = pn.test_k._replace(noise_floor=None), pc.test_k  # dn: the floor read off residuals
        unit = dn.k * pn.sm.robot.ctrl_dt * pn.scale  # the residual's per-dof scaling
        rn, rc = fit.residual(pn.sm, plan, dn, pn.scale), fit.residual(pn.sm, plan, dc, pn.scale)
        gn, gc = fit.gap(rn), fit.gap(rc)
        true_s2 = ((dn.qd - dc.qd) ** 2).mean(0) / unit ** 2  # the noise the sensors added
        # the noise level the logs themselves show (second differences, as the preprocessing reports)
        est_s2 = filters.noise_std(np.concatenate([t.qd for t in pn.trajs])) ** 2 / unit ** 2
        ac = acov_k(rn, dn)
        out = dict(case=index, planted=gbi.cases(cfg)[index]["planted"], k=dn.k,
                   gap_noisy=round(gn, 4), gap_clean=round(gc, 4), noise_part=round(gn - gc, 4),
                   floor_tool=round(regions.noise_floor(rn, dn), 4),
                   # J = 1 (an initial velocity error kept over the replay): 2 sigma^2 per dof
                   floor_2sigma_true=round(float(2 * true_s2.sum()), 4),
                   floor_2sigma_logs=round(float(2 * est_s2.sum()), 4),
                   floor_max_logs=round(float(np.maximum(est_s2, -2 * ac).sum()), 4),
                   floor_from_spec=round(floor_from_spec, 4))
        print(json.dumps(out), flush=True)


if __name__ == "__main__":
    main([int(a) for a in sys.argv[1:]])
