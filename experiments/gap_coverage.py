"""Coverage of the gap tool's parameter intervals over repeated noisy draws (issue 18, item 3).

    python experiments/gap_coverage.py --draws 30 --out results/gap_coverage [--trajectories 4 --steps 100]

For each planted effect (one at a time, on the pendulum, through a real robot's sensors:
``real.SensorNoise``), ``--draws`` independent logs are generated and the effect alone is fitted with
the ``tiny`` preset's fit settings; the 90% interval should cover the planted value in about 90% of
draws. Besides the coverage each row gives the estimate's bias in standard errors (median estimate
minus truth, over the median half width / 1.645): the intervals hold sampling noise only, so a bias
from noise in the replayed start states (errors in variables) lowers coverage as the logs grow.
Writes ``<out>/coverage.{md,json}``.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time

import numpy as np

# planted values: the tiny benchmark's smaller magnitudes (stride_jax/jobs/gap_bench.py)
PLANTED = {"damping": 0.3, "frictionloss": 0.15, "armature": 0.05, "torque_scale": 0.85, "payload": 0.15,
           "torque_limit": 0.7, "deadzone": 0.3}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=30)
    ap.add_argument("--trajectories", type=int, default=4)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--effects", default=",".join(PLANTED))
    ap.add_argument("--out", default="results/gap_coverage")
    a = ap.parse_args()
    from tqdm import tqdm

    from stride_jax.gap import diagnose, effects, filters, fit, real
    from stride_jax.io import atomic_write_text
    from stride_jax.sim import model

    cfg = diagnose.PRESETS["tiny"]
    sm = model.load("pendulum")
    rows = []
    t0 = time.time()
    for name in a.effects.split(","):
        true = PLANTED[name]
        lo_b, hi_b = (float(b[0]) for b in effects.ALL[name].bounds(sm))
        est, lo, hi = [], [], []
        for seed in tqdm(range(a.draws), desc=name):
            _, logged = real.generate(sm, {name: true}, a.trajectories, a.steps, seed=1000 + seed,
                                      noise=real.SensorNoise())
            logged = [filters.preprocess(t, sm.robot.ctrl_dt, cfg.preprocess)[0] for t in logged]
            data = fit.make_data(logged, cfg.steps)
            f = fit.fit(sm, data, diagnose.scale_of(sm, data), (name,), cfg.fit)
            est.append(float(f.params[name][0]))
            lo.append(float(f.lo[name][0]))
            hi.append(float(f.hi[name][0]))
        est, lo, hi = map(np.asarray, (est, lo, hi))
        half = np.median((hi - lo) / 2)
        rows.append({"effect": name, "planted": true, "draws": a.draws,
                     "covered": int(((lo <= true) & (true <= hi)).sum()),
                     "contains_estimate": int(((lo <= est) & (est <= hi)).sum()),
                     "inside_bounds": int(((lo_b <= lo) & (hi <= hi_b)).sum()),
                     "mean_estimate": float(est.mean()), "median_estimate": float(np.median(est)),
                     "sd_estimate": float(est.std(ddof=1)),
                     "robust_sd_estimate": float(1.4826 * np.median(np.abs(est - np.median(est)))),
                     "median_half_width": float(half),
                     "bias_in_se": float((np.median(est) - true) / max(half / 1.645, 1e-300)),
                     "low_misses": int((true < lo).sum()), "high_misses": int((true > hi).sum()),
                     "estimates": est.tolist(), "lo": lo.tolist(), "hi": hi.tolist()})
    out = pathlib.Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    cmd = (f"python experiments/gap_coverage.py --draws {a.draws} --trajectories {a.trajectories} "
           f"--steps {a.steps} --effects {a.effects} --out {a.out}")
    lines = ["# Coverage of the gap tool's 90% parameter intervals (pendulum, sensor noise)", "",
             f"Command: `{cmd}` ({time.time() - t0:.0f} s)", "",
             f"{a.draws} independent noisy draws of {a.trajectories} x {a.steps} control steps per effect, "
             "the effect fitted alone with the `tiny` preset's fit settings. Bias: median estimate minus the "
             "planted value, in standard errors (median half width / 1.645); sd: the estimates' spread over "
             "the draws (1.4826 x their median absolute deviation: a failed fit does not dominate it), which a "
             "right interval's half width / 1.645 matches. Misses below / above: the "
             "planted value under the interval / over it.", "",
             "| effect | planted | covered | contains its estimate | inside the bounds | median estimate | sd | "
             "median half width | bias (se) | misses below / above |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['effect']} | {r['planted']:g} | {r['covered']}/{r['draws']} "
                     f"({r['covered'] / r['draws']:.0%}) | {r['contains_estimate']}/{r['draws']} | "
                     f"{r['inside_bounds']}/{r['draws']} | {r['median_estimate']:.4g} | {r['robust_sd_estimate']:.3g} | "
                     f"{r['median_half_width']:.3g} | "
                     f"{r['bias_in_se']:+.2f} | {r['low_misses']} / {r['high_misses']} |")
    atomic_write_text(out / "coverage.md", "\n".join(lines) + "\n")
    atomic_write_text(out / "coverage.json", json.dumps({"command": cmd, "rows": rows}, indent=1))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
