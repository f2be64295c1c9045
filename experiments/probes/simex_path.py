"""The SIMEX path by hand: does a fit's estimate rise with velocity noise added to the logs?

Per draw of noisy pendulum logs (damping 0.3 planted, 8 x 150 steps, ``real.SensorNoise()``, the
`tiny` preset's fits, the logs of ``experiments/gap_coverage.py``'s draws), the damping fit, then
refits on the logs with white noise of ``level`` times their own velocity-noise variance added
(``simex.with_noise``), started from the estimate (as ``simex.correct`` refits) and from scratch.
An errors-in-variables bias shows as estimates rising with the level.

    python experiments/probes/simex_path.py [--draws 3] [--levels 1,2]
"""

from __future__ import annotations

import argparse

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=3)
    ap.add_argument("--levels", default="1,2", help="added variances, in units of the logs' own")
    a = ap.parse_args()
    from stride_jax.gap import diagnose, filters, fit, real, simex
    from stride_jax.sim import model

    cfg = diagnose.PRESETS["tiny"]
    sm = model.load("pendulum")
    for seed in range(a.draws):
        _, logged = real.generate(sm, {"damping": 0.3}, 8, 150, seed=1000 + seed, noise=real.SensorNoise())
        logged = [filters.preprocess(t, sm.robot.ctrl_dt, cfg.preprocess)[0] for t in logged]
        data = fit.make_data(logged, cfg.steps)
        scale = diagnose.scale_of(sm, data)
        f = fit.fit(sm, data, scale, ("damping",), cfg.fit, interval=False)
        sd = simex.velocity_noise(data)
        rng = np.random.default_rng(seed)
        for level in (float(x) for x in a.levels.split(",")):
            noisier = simex.with_noise(data, sd, level, rng)
            warm = fit.fit(sm, noisier, scale, ("damping",), cfg.fit, f.params, interval=False).params["damping"]
            cold = fit.fit(sm, noisier, scale, ("damping",), cfg.fit, interval=False).params["damping"]
            print(f"draw {seed}: estimate {f.params['damping'][0]:.5f} (velocity noise {sd[0]:.4f}); "
                  f"level {level:g}: from the estimate {warm[0]:.5f}, from scratch {cold[0]:.5f}", flush=True)


if __name__ == "__main__":
    main()
