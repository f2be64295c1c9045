"""Coverage of the gap tool's parameter intervals over repeated noisy draws (issue 18, item 3).

    python experiments/gap_coverage.py --draws 30 --out results/gap_coverage [--trajectories 4 --steps 100]
        [--effects damping,delay,com_offset,damping+delay,payload+torque_scale] [--simex 4]
        [--noise outlier_rate=0,torque_std=0 | --noise none]
    python experiments/gap_coverage.py --robot go1 --draws 20 --out results/gap_coverage/go1

For each planted effect or pair (one case at a time, on the pendulum or the Go1 -- its MJX-training
form, whose replays are ~6x cheaper than the shipped model's --, through a real robot's sensors:
``real.SensorNoise``), ``--draws`` independent logs are generated with the robot's explorer and the
case's effects are fitted with the ``--preset``'s fit settings (the pendulum: ``tiny``, the Go1:
``fast``, the independent benchmark's); the 90% interval of every parameter should cover its
planted value in about 90% of draws. The logs come from the nominal model itself with the effect
planted: sampling noise only, no model-form difference (the independent benchmark's part). Scalars get the profile interval (or, where the loss is
kinked or few blocks inform it, the test inversion), the delay its integer set, a vector (the centre
of mass offset, one row per component) and a pair the sandwich interval; a pair is fitted as a
diagnosis fits it, from its two singles' estimates. Besides the coverage each row gives the
estimate's bias in standard errors (median estimate minus truth, over the median half width /
1.645): the intervals hold sampling noise only, so a bias lowers coverage as the logs grow.
``--simex N`` tests whether that bias is the velocity noise in the replayed start states (errors in
variables) by simulation-extrapolation (:mod:`stride_jax.gap.simex`: N refits per added noise
level, ``--simex-degree``: a quadratic or a line in the added variance), moving the interval with
the estimate (continuous effects; a delay is left as fitted); session 53 read its run as "it is
not"; session 55 measured that it is (the bias grows with the velocity noise's variance, and a
line's SIMEX removes it: ``results/gap_coverage/noise_terms``). ``--noise``
changes terms of ``real.SensorNoise`` (``name=value,...``; ``none``: noise-free logs), to find
which sensor term a bias comes from. Writes ``<out>/coverage.{md,json}``.
"""

from __future__ import annotations

import argparse
import dataclasses
import pathlib
import time

import numpy as np

from stride_jax import config

# planted values: on the pendulum the tiny benchmark's smaller magnitudes (stride_jax/jobs/gap_bench.py),
# on the Go1 the independent benchmark's singles (stride_jax/jobs/gap_bench_independent.py; delay in
# control steps here)
PLANTED = {
    "pendulum": {"damping": 0.3, "frictionloss": 0.15, "armature": 0.05, "torque_scale": 0.85, "payload": 0.15,
                 "torque_limit": 0.7, "deadzone": 0.3, "delay": 2, "com_offset": (0.03, 0.0, 0.0)},
    "go1": {"damping": 1.5, "frictionloss": 0.8, "armature": 0.04, "torque_scale": 0.65, "payload": 2.5,
            "torque_limit": 0.4, "kp_scale": 0.7, "ground_friction": 0.3, "delay": 2,
            "com_offset": (0.03, 0.0, 0.0)}}
SCALARS = {"pendulum": "damping,frictionloss,armature,torque_scale,payload,torque_limit,deadzone",
           "go1": "damping,frictionloss,armature,torque_scale,payload,torque_limit,kp_scale,ground_friction"}
DEFAULTS = {"pendulum": dict(trajectories=4, steps=100, preset="tiny"),
            "go1": dict(trajectories=6, steps=200, preset="fast")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robot", default="pendulum", choices=sorted(PLANTED))
    ap.add_argument("--draws", type=int, default=30)
    ap.add_argument("--trajectories", type=int, default=0, help="per draw (0: the robot's default, 4 / 6)")
    ap.add_argument("--steps", type=int, default=0, help="control steps per trajectory (0: 100 / 200)")
    ap.add_argument("--preset", default="", help="the diagnosis preset whose fit settings are used (tiny / fast)")
    ap.add_argument("--effects", default="", help="comma-separated effects of PLANTED, or pairs a+b "
                    "(default: the robot's scalars)")
    ap.add_argument("--simex", type=int, default=0, help="SIMEX refits per noise level (0: none)")
    ap.add_argument("--simex-degree", type=int, default=2, choices=(1, 2),
                    help="SIMEX's extrapolant in the added variance: a quadratic (2) or a line (1)")
    ap.add_argument("--noise", default="",
                    help="changes to real.SensorNoise's terms, name=value,... ('none': no noise)")
    ap.add_argument("--out", default="results/gap_coverage")
    a = ap.parse_args()
    for name, value in DEFAULTS[a.robot].items():
        if not getattr(a, name):
            setattr(a, name, value)
    a.effects = a.effects or SCALARS[a.robot]
    planted = PLANTED[a.robot]
    from tqdm import tqdm

    from stride_jax.gap import diagnose, effects, filters, fit, real, simex
    from stride_jax.io import code_version, write_table
    from stride_jax.sim import model

    noise = sensor_noise(real, a.noise)
    version = code_version()  # before the run: the checkout may change while it runs
    if a.preset not in diagnose.PRESETS:
        raise SystemExit(f"--preset {a.preset!r}: one of {', '.join(diagnose.PRESETS)}")
    cfg = diagnose.PRESETS[a.preset]
    sm = model.load(a.robot)
    rows = []
    t0 = time.time()
    for case in a.effects.split(","):
        names = tuple(case.split("+"))
        unknown = [n for n in names if n not in planted]
        if unknown:
            raise SystemExit(f"no planted value for {unknown} on the {a.robot}; known: {', '.join(planted)}")
        truth = {n: np.atleast_1d(np.asarray(planted[n], float)) for n in names}
        draws = []  # per draw: {name: (estimate, lo, hi)} vectors
        for seed in tqdm(range(a.draws), desc=case):
            _, logged = real.generate(sm, {n: planted[n] for n in names}, a.trajectories, a.steps,
                                      seed=1000 + seed, noise=noise)
            logged = [filters.preprocess(t, sm.robot.ctrl_dt, cfg.preprocess)[0] for t in logged]
            data = fit.make_data(logged, cfg.steps)
            scale = diagnose.scale_of(sm, data)
            start = None
            if len(names) > 1:  # as a diagnosis fits a pair: from its singles' estimates
                start = {n: fit.fit(sm, data, scale, (n,), cfg.fit, interval=False).params[n] for n in names}
            f = fit.fit(sm, data, scale, names, cfg.fit, start)
            est, lo, hi = f.params, f.lo, f.hi
            if a.simex and not any(effects.ALL[n].integer for n in names):
                refit = lambda d: fit.fit(sm, d, scale, names, cfg.fit, f.params, interval=False).params
                corrected, _ = simex.correct(refit, data, f.params, simex.SimexConfig(draws=a.simex, seed=seed,
                                                                                         degree=a.simex_degree))
                est, lo, hi = simex.shifted(f.params, f.lo, f.hi, corrected,
                                            {n: effects.ALL[n].bounds(sm) for n in names})
            draws.append({n: tuple(np.asarray(v[n], float) for v in (est, lo, hi)) for n in names})
        for n in names:
            lo_b, hi_b = (np.asarray(b, float) for b in effects.ALL[n].bounds(sm))
            for i, label in enumerate(effects.ALL[n].labels):
                true = float(truth[n][i])
                est, lo, hi = (np.array([d[n][j][i] for d in draws]) for j in range(3))
                half = np.median((hi - lo) / 2)
                rows.append({"effect": n if len(names) == 1 else f"{n} (with {'+'.join(m for m in names if m != n)})",
                             "case": case, "parameter": label if len(truth[n]) > 1 else "",
                             "planted": true, "draws": a.draws,
                             "covered": int(((lo <= true) & (true <= hi)).sum()),
                             "contains_estimate": int(((lo <= est) & (est <= hi)).sum()),
                             "inside_bounds": int(((lo_b[i] <= lo) & (hi <= hi_b[i])).sum()),
                             "mean_estimate": float(est.mean()), "median_estimate": float(np.median(est)),
                             "sd_estimate": float(est.std(ddof=1)),
                             "robust_sd_estimate": float(1.4826 * np.median(np.abs(est - np.median(est)))),
                             "median_half_width": float(half),
                             "bias_in_se": float((np.median(est) - true) / max(half / 1.645, 1e-300)),
                             "low_misses": int((true < lo).sum()), "high_misses": int((true > hi).sum()),
                             "estimates": est.tolist(), "lo": lo.tolist(), "hi": hi.tolist()})
    out = pathlib.Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    cmd = (f"python experiments/gap_coverage.py" + (f" --robot {a.robot}" if a.robot != "pendulum" else "")
           + (f" --preset {a.preset}" if a.preset != DEFAULTS[a.robot]["preset"] else "")
           + f" --draws {a.draws} --trajectories {a.trajectories} "
           f"--steps {a.steps} --effects {a.effects}" + (f" --simex {a.simex}" if a.simex else "")
           + (f" --simex-degree {a.simex_degree}" if a.simex and a.simex_degree != 2 else "")
           + (f" --noise {a.noise}" if a.noise else "") + f" --out {a.out}")
    lines = [f"# Coverage of the gap tool's 90% parameter intervals ({a.robot}, sensor noise)", "",
             f"Sensor noise: {noise_text(noise)}", "",
             f"Command: `{cmd}` ({time.time() - t0:.0f} s; code {version})", "",
             f"{a.draws} independent noisy draws of {a.trajectories} x {a.steps} control steps per case, "
             f"the case's effects fitted with the `{a.preset}` preset's fit settings (a pair jointly, from its singles' "
             "estimates)" + (f"; estimates and intervals corrected by SIMEX ({a.simex} refits per added noise "
                            f"level, {'a line' if a.simex_degree == 1 else 'a quadratic'} in the added "
                            "variance; a delay as fitted)" if a.simex else "") + ". Bias: median estimate minus the "
             "planted value, in standard errors (median half width / 1.645); sd: the estimates' spread over "
             "the draws (1.4826 x their median absolute deviation: a failed fit does not dominate it), which a "
             "right interval's half width / 1.645 matches. Misses below / above: the "
             "planted value under the interval / over it.", "",
             "| effect | planted | covered | contains its estimate | inside the bounds | median estimate | sd | "
             "median half width | bias (se) | misses below / above |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        label = r["effect"] + (f" [{r['parameter']}]" if r.get("parameter") else "")
        lines.append(f"| {label} | {r['planted']:g} | {r['covered']}/{r['draws']} "
                     f"({r['covered'] / r['draws']:.0%}) | {r['contains_estimate']}/{r['draws']} | "
                     f"{r['inside_bounds']}/{r['draws']} | {r['median_estimate']:.4g} | {r['robust_sd_estimate']:.3g} | "
                     f"{r['median_half_width']:.3g} | "
                     f"{r['bias_in_se']:+.2f} | {r['low_misses']} / {r['high_misses']} |")
    write_table(out / "coverage", {"command": cmd, "code": version, "rows": rows},
                "\n".join(lines) + "\n")
    print("\n".join(lines))


def sensor_noise(real, spec: str):
    """``real.SensorNoise`` with the terms of ``spec`` (``name=value,...``, each value read as its
    field's type: ``stride_jax.config.flag_names``) changed; None for ``none`` (noise-free logs).
    An unknown term or a value of the wrong type is an error naming it."""
    if spec.strip().lower() == "none":
        return None
    kinds = {dest: kind for dest, (_, kind, _) in config.flag_names(real.SensorNoise).items()}
    changes = {}
    for item in filter(None, (x.strip() for x in spec.split(","))):
        name, eq, value = item.partition("=")
        if not eq or name not in kinds:
            raise SystemExit(f"--noise: {item!r} is not NAME=VALUE with NAME one of {', '.join(kinds)}")
        try:
            changes[name] = kinds[name](value)
        except ValueError:
            raise SystemExit(f"--noise: {name}={value!r} is not a number ({kinds[name].__name__})") from None
    return config.replace(real.SensorNoise(), changes)


def noise_text(noise) -> str:
    """The sensor noise a run used, in words (every term, the defaults included)."""
    if noise is None:
        return "none (noise-free logs)"
    return ", ".join(f"{f.name} {getattr(noise, f.name):g}" for f in dataclasses.fields(noise))


if __name__ == "__main__":
    main()
