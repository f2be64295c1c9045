"""The calibration of one noisy case of the independent gap benchmark at several ``min_gain``: is
the noisy frictionloss miss the calibration's threshold? (session 49)

    python experiments/probes/calibration_min_gain.py CASE GAIN[,GAIN...]   # e.g. 2 0.01,0.004

Prints the k-step noise floor read off the nominal model's training residuals, then per
``min_gain``: the settings changed, and the held-out k-step gap of the calibrated model (with the
refinement, as the diagnosis runs it) on the clean twins and on the noisy logs, without and with
the planted effect (its share closed). The noise that enters the noisy logs' training loss (about
half of it after calibration) dilutes the relative ``min_gain``: 0.004 on noisy logs is about 0.01
on the clean twins' loss.
"""
import dataclasses
import json
import sys
import time

from stride_jax.gap import baseline, calibrate, diagnose, effects, fit, regions
from stride_jax.jobs import gap_bench_independent as bi

case = int(sys.argv[1])
gains = [float(g) for g in sys.argv[2].split(",")]
cfg = bi.PRESETS["default"]
dcfg = diagnose.PRESETS[cfg.diagnose]
planted = json.load(open(f"results/gap_bench_go1_independent_cases/{case:02d}-noisy.json"))["row"]["planted"]
sm, trajs, clean, *_ = bi.as_read(cfg, case, True)
p, pc = diagnose.prepare(sm, trajs, dcfg), diagnose.prepare(sm, clean, dcfg)
r_tr = fit.residual(p.sm, effects.build(p.sm), p.train_k, p.scale)
print("k-step floor (residual autocov) train:", regions.noise_floor(r_tr, p.train_k), "loss", fit.gap(r_tr))
for g in gains:
    t0 = time.time()
    cc = dataclasses.replace(dcfg.calibrate, min_gain=g)
    cal = calibrate.calibrate(p.sm, p.train_k, p.test_k, p.scale, cc, log=lambda s: None)
    if cc.refine:
        cal = calibrate.refine(p.sm, cal, p.train_k, p.test_k, p.scale, cc, dcfg.fit.grid, log=lambda s: None)
    m = cal.model
    gc, gcp = (fit.gap(baseline.residual(m, pc.test_k, p.scale, a)) for a in (None, planted))
    gn, gnp = (fit.gap(baseline.residual(m, p.test_k, p.scale, a)) for a in (None, planted))
    print(f"min_gain {g}: {cal.record['changed']} | clean test {gc:.4f} +planted {gcp:.4f} ({1-gcp/gc:.0%}) | "
          f"noisy test {gn:.4f} +planted {gnp:.4f} ({1-gnp/gn:.0%}) | {time.time()-t0:.0f} s", flush=True)
