"""Is a miss of the calibration its search or the logs? On one row of the independent gap
benchmark (clean or noisy logs), the training loss of the simulator's settings found by the
calibration's search (:func:`stride_jax.gap.calibrate.in_turns`: the discrete settings first, at
the nominal contact parameters) from the shipped model and from its MJX-training form, against the
loss at the drawn "real" settings themselves (expressed as calibration settings; solimp's d0 and
dmax with their own factors) and against a second start: the continuous contact settings fitted
first at the shipped discrete settings, then the same search.

    python experiments/probes/calibration_starts.py --preset controls --case 19 [--noisy]

Session 52 found control 19's calibration in the pyramidal cone with condim 3 while the drawn
settings replay its logs exactly (``docs/gap.md``, "Detection"). Run it alone on the 2-core
machine: about a minute a row.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import stride_jax
from stride_jax.gap import calibrate as C, nominal
from stride_jax.gap.baseline import residual
from stride_jax.gap.nominal import Settings
from stride_jax.jobs import gap_bench_independent as bi


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", type=int, required=True)
    ap.add_argument("--noisy", action="store_true")
    ap.add_argument("--preset", default="controls", help="the benchmark's preset (its cases)")
    a = ap.parse_args()
    from calibration_with_effect import row_data  # a probe beside this one

    p, cfg, drawn = row_data(bi.PRESETS[a.preset], a.case, a.noisy)
    sm, cc = p.sm, cfg.calibrate
    sub = C._sub(p.train_k, C.stride(cc, len(p.train_k.start)))
    own = nominal.describe(sm)
    cache, evals = C.ByModel(own), {"n": 0}

    def loss(s: Settings) -> float:
        if s not in cache:
            cache[s] = float((residual(nominal.apply(sm, s), sub, p.scale, None) ** 2).sum())
        return cache[s]

    training = nominal.training_settings(sm, nominal.load(sm.robot.name, "training"))
    values = {"timestep": [v for v in nominal.timesteps(sm, cc.timestep_min, cc.timestep_max)
                           if abs(v * 2e3 - round(v * 2e3)) < 1e-6],
              "integrator": C._names(cc.integrators), "cone": list(nominal.CONES), "contacts": list(nominal.CONTACTS),
              "foot_condim": [3, 6], "iterations": sorted({training.iterations} - {None})}
    for n in values:
        if values[n] and own.get(n) is not None and own[n] not in values[n]:
            values[n].append(own[n])
    cont = C._names(cc.continuous)
    fit_cont = lambda s: C.fit_continuous(sm, s, sub, p.scale, cont, cc.max_nfev, None, cache, evals)[:2]
    full = lambda s: dataclasses.replace(s, **{n: own[n] for n in C.DISCRETE
                                               if getattr(s, n) is None and own.get(n) is not None})
    show = lambda s: "; ".join(nominal.summary(C._neutral(s, own), sm)) or "none"
    print(f"case {a.case} ({'noisy' if a.noisy else 'clean'}), planted {bi.cases(bi.PRESETS[a.preset])[a.case]['planted']}, "
          f"drawn {drawn}")
    print(f"training loss: nominal {loss(Settings()):.5g}, MJX-training form {loss(training):.5g}")
    if not (set(drawn) - {"timestep", "integrator", "cone", "feet_only", "solref_timeconst_factor",
                          "solref_dampratio_factor", "solimp_d0_factor", "solimp_dmax_factor", "solimp_width_factor",
                          "margin_added", "impratio"}):
        truth = Settings(timestep=drawn.get("timestep"), integrator=drawn.get("integrator"), cone=drawn.get("cone"),
                         contacts="feet_only" if drawn.get("feet_only") else None,
                         **({} if "impratio" not in drawn else dict(
                             solref_timeconst=drawn["solref_timeconst_factor"],
                             solref_dampratio=drawn["solref_dampratio_factor"], solimp_d0=drawn["solimp_d0_factor"],
                             solimp_dmax=drawn["solimp_dmax_factor"], solimp_width=drawn["solimp_width_factor"],
                             margin=drawn["margin_added"], impratio=drawn["impratio"] / sm.mj.opt.impratio)))
        print(f"at the drawn settings: {loss(truth):.5g}")
    starts = {"shipped": Settings(), "MJX-training form": training}
    for name, start in starts.items():
        t0 = time.time()
        best, _, _ = C.in_turns(full(start), values, own, loss, fit_cont, cont, cc, [])
        print(f"search from the {name}: {loss(best):.5g}; {show(best)} ({time.time() - t0:.0f} s)", flush=True)
    t0 = time.time()
    s1, L1 = fit_cont(Settings())
    best, _, _ = C.in_turns(full(s1), values, own, loss, fit_cont, cont, cc, [])
    print(f"continuous first ({L1:.5g}), then the search: {loss(best):.5g}; {show(best)} ({time.time() - t0:.0f} s)")


if __name__ == "__main__":
    stride_jax.set_xla_flags()
    main()
