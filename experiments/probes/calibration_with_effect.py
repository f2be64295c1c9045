"""Does a physical effect that the contact calibration can imitate fit better *inside* the
calibration than after it? On one row of the independent gap benchmark, the simulator's settings
are calibrated as `stride gap diagnose` does (the benchmark's diagnosis preset), and again with
each given effect held fixed on top (``calibrate(applied=...)``); prints the held-out k-step gap
of each (lower: the logs prefer it) and the settings each found.

    python experiments/probes/calibration_with_effect.py --case 8 [--noisy] \
        --effects "ground_friction=0.3;ground_friction=0.5"

``--shares`` instead prints, for every row of the benchmark (clean and noisy), the share of the
nominal model's training loss that the contact effects without a setting (ground friction) close
on their own: the refinement's second start (``calibrate._contact_effect_start``) runs only where
it reaches ``--calibrate.second-start`` (0.5), so rows below it diagnose as before the second
start existed.

Run it alone on the 2-core machine: each calibration takes 1-3 minutes, ``--shares`` ~10 s a row.
"""

from __future__ import annotations

import argparse
import time

import stride_jax
from stride_jax.gap import calibrate, diagnose
from stride_jax.jobs import gap_bench_independent as bi


def row_data(bcfg, case: int, noisy: bool):
    """A benchmark row's logs as ``diagnose`` prepares them, its diagnosis config and the drawn
    settings."""
    sm, trajs, _, settings, _, velocity_std = bi.as_read(bcfg, case, noisy)
    cfg = diagnose.PRESETS[bcfg.diagnose]
    return diagnose.prepare(sm, trajs, cfg, velocity_std), cfg, settings


def shares(bcfg) -> None:
    for case in range(len(bi.cases(bcfg))):
        for noisy in bcfg.noise:
            p, cfg, _ = row_data(bcfg, case, noisy)
            alt, _, share = calibrate.contact_effect_screen(p.sm, p.train_k, p.scale, cfg.calibrate, cfg.fit.grid)
            print(f"case {case:2d} {'noisy' if noisy else 'clean'} planted {bi.cases(bcfg)[case]['planted']}: "
                  f"{alt or 'no gain'}, share {share:.1%}" + ("  <- second start" if share >= cfg.calibrate.second_start
                                                                 else ""), flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", type=int, default=-1)
    ap.add_argument("--noisy", action="store_true")
    ap.add_argument("--preset", default="default", help="the benchmark's preset (its cases)")
    ap.add_argument("--effects", default="", help="'name=value;...': each held fixed in its own calibration")
    ap.add_argument("--shares", action="store_true", help="every row's second-start share instead")
    a = ap.parse_args()
    bcfg = bi.PRESETS[a.preset]
    if a.shares:
        return shares(bcfg)
    if a.case < 0:
        ap.error("--case is required without --shares")
    p, cfg, settings = row_data(bcfg, a.case, a.noisy)
    print(f"case {a.case} ({'noisy' if a.noisy else 'clean'}): planted {bi.cases(bcfg)[a.case]['planted']}, "
          f"drawn settings {settings}", flush=True)
    runs = [("settings only", None)]
    for item in filter(None, a.effects.split(";")):
        name, value = item.split("=")
        runs.append((item, {name.strip(): [float(value)]}))
    for label, applied in runs:
        t0 = time.time()
        cal = calibrate.calibrate(p.sm, p.train_k, p.test_k, p.scale, cfg.calibrate, log=lambda s: None,
                                  applied=applied)
        print(f"{label:28s} held-out {p.test_k.k}-step gap {calibrate.heldout_gap(cal):.5g} (nominal settings, "
              f"nothing applied: {cal.record['heldout_gap_nominal']:.5g}); {'; '.join(cal.record['proposed'])} "
              f"({time.time() - t0:.0f} s)", flush=True)

if __name__ == "__main__":
    stride_jax.set_xla_flags()
    main()
