"""How far does a named effect's estimate move between the logged trajectories, against its
interval? On rows of the independent gap benchmark (logs whose simulator differs from the nominal
model), the planted effect is fitted on the row's calibrated baseline (its committed
``calibration_settings``) from all training trajectories -- the diagnosis's estimate and interval --
and from each training trajectory alone. Where the model-form difference left after calibration
biases the estimate, the bias differs between motions: the trajectories' spread then measures it,
where the block intervals (sampling noise) do not.

    python experiments/probes/form_spread.py --rows 01-clean,05-clean,09-clean [--cases DIR]
        [--nominal] [--alternatives] [--profile 1.4,1.46,1.5,1.55] [--no-trajectories]

Prints one line per fit; each row takes ~1-3 minutes on 2 cores.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time

import numpy as np

import stride_jax
from stride_jax.gap import diagnose, fit, nominal, screen
from stride_jax.jobs import gap_bench_independent as bi


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", required=True, help="comma-separated NN-clean / NN-noisy")
    ap.add_argument("--cases", default="results/gap_bench_go1_independent_cases")
    ap.add_argument("--preset", default="default", help="the benchmark's preset (its cases)")
    ap.add_argument("--nominal", action="store_true", help="also fit on the nominal (uncalibrated) model")
    ap.add_argument("--no-trajectories", action="store_true", help="skip the per-trajectory fits")
    ap.add_argument("--profile", default="", help="comma-separated values of the (single) planted effect: its "
                    "training loss at each with the settings fixed and with the continuous contact settings refitted")
    ap.add_argument("--alternatives", action="store_true",
                    help="also refit the effect on every other value of each discrete setting")
    a = ap.parse_args()
    bcfg = bi.PRESETS[a.preset]
    cfg = diagnose.PRESETS[bcfg.diagnose]
    for name in a.rows.split(","):
        row = json.loads((pathlib.Path(a.cases) / f"{name}.json").read_text())["row"]
        case, noisy = row["case"], row["noisy"]
        sm, trajs, _, _, _, velocity_std = bi.as_read(bcfg, case, noisy)
        p = diagnose.prepare(sm, trajs, cfg, velocity_std)
        s = nominal.Settings(**{k: v for k, v in row["calibration_settings"].items() if v is not None})
        base = nominal.apply(p.sm, s)
        stride = screen.fit_stride_of(cfg.screen, len(p.train_k.start))
        for eff, truth in row["planted"].items():
            t0 = time.time()
            whole = fit.fit(base, fit.thin(p.train_k, stride), p.scale, (eff,), cfg.fit)
            print(f"{name} {eff} truth {truth}: all {len(p.tr_idx)} training trajectories "
                  f"{whole.params[eff]} [{whole.lo[eff]}, {whole.hi[eff]}] ({time.time() - t0:.0f} s)", flush=True)
            if a.profile:
                profile(p, s, base, eff, [float(v) for v in a.profile.split(",")], stride, cfg)
            if a.nominal:
                f = fit.fit(p.sm, fit.thin(p.train_k, stride), p.scale, (eff,), cfg.fit)
                print(f"  nominal model: {f.params[eff]} [{f.lo[eff]}, {f.hi[eff]}], training loss x "
                      f"{f.train_loss / whole.train_loss:.4f}", flush=True)
            if a.alternatives:
                alternatives(base, p, s, eff, whole, stride, cfg)
            if a.no_trajectories:
                continue
            ests = []
            for i in p.tr_idx:
                d = fit.make_data([p.trajs[i]], cfg.steps)
                f = fit.fit(base, fit.thin(d, stride), p.scale, (eff,), cfg.fit)
                ests.append(f.params[eff])
                print(f"  trajectory {i}: {f.params[eff]} [{f.lo[eff]}, {f.hi[eff]}]", flush=True)
            E = np.array(ests)
            n = len(E)
            print(f"  spread over trajectories: mean {E.mean(0)}, sd {E.std(0, ddof=1)}, "
                  f"se of the mean {E.std(0, ddof=1) / np.sqrt(n)}; the interval's half width "
                  f"{(np.asarray(whole.hi[eff]) - np.asarray(whole.lo[eff])) / 2}", flush=True)


def profile(p, s, base, eff, values, stride, cfg) -> None:
    """The effect's training loss at ``values``: on the calibrated settings as they are, and with the
    continuous contact settings fitted again at each value (a profile over those nuisance settings)."""
    from stride_jax.gap import baseline, calibrate
    data = fit.thin(p.train_k, stride)
    cont = calibrate._names(cfg.calibrate.continuous)
    for v in values:
        app = {eff: [v]}
        fixed = float((baseline.residual(base, data, p.scale, app) ** 2).sum())
        _, refit, _ = calibrate.fit_continuous(p.sm, s, data, p.scale, cont, cfg.calibrate.max_nfev, app)
        print(f"  {eff}={v}: training loss {fixed:.5g} on the calibrated settings, {refit:.5g} with the contact "
              f"settings refitted", flush=True)


def alternatives(base, p, s, eff, whole, stride, cfg) -> None:
    """The effect refitted with one discrete setting changed at a time (the rest as calibrated)."""
    import dataclasses
    values = {"timestep": nominal.timesteps(p.sm), "integrator": list(nominal.INTEGRATORS),
              "cone": list(nominal.CONES), "contacts": list(nominal.CONTACTS), "foot_condim": [1, 3, 4, 6]}
    data = fit.thin(p.train_k, stride)
    for name, vals in values.items():
        for v in vals:
            if getattr(s, name) == v:
                continue
            try:
                alt = nominal.apply(p.sm, dataclasses.replace(s, **{name: v}))
            except ValueError:
                continue
            f = fit.fit(alt, data, p.scale, (eff,), cfg.fit)
            print(f"  {name}={v}: {f.params[eff]} [{f.lo[eff]}, {f.hi[eff]}], training loss x "
                  f"{f.train_loss / whole.train_loss:.4f}", flush=True)


if __name__ == "__main__":
    stride_jax.set_xla_flags()
    main()
