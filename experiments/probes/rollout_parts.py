"""Where a trained model's open-loop error lies, by part of the state, on any dataset of its robot.

For each run (``stride train`` folder), on the test split of ``--data`` (the runs' own training
data need not be here; observation scales from its train split):

* the cumulative normalised ``--horizon``-step rollout RMSE (Table I's state metric) from
  ``--windows`` windows: stochastic models once per ``--samples`` latent draws (``latents
  "step"``, as Table I) and once with the residual's central sample at every step (``"central"``,
  what ``MPPIConfig(latents="central")`` plans with); deterministic models once; with each
  part's RMS over the horizon and share of the squared error (the floating base's position,
  orientation, linear and angular velocity; the joints' angles and rates);
* the one-control-period velocity error per part (central sample), in standard deviations of
  the velocities: how far one step is off before errors compound;
* for structured models, the instantaneous acceleration error at the recorded states (their
  training target, MuJoCo's ``qacc``), in standard deviations of ``qacc``;
* the data's own gap between the two targets: the period-average acceleration
  ``(qd' - qd) / ctrl_dt`` against the instantaneous ``qacc`` at the period's start.

Prints and writes ``--out`` (JSON).

    python experiments/probes/rollout_parts.py --data /tmp/g1_walk_mjx \\
        --runs results/models/g1_walk/stride-s0,results/models/g1_walk/delan-s0,results/models/g1_walk/onn-s0
"""

from __future__ import annotations

import argparse
import json
import pathlib
import shlex
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from stride_jax.dynamics import checkpoint, models
from stride_jax.eval import rollout
from stride_jax.io import atomic_write_text, code_version
from stride_jax.sim import dataset


def groups(nv: int, floating_base: bool, velocity_only: bool = False) -> dict[str, np.ndarray]:
    """Entries of a normalised error ``[2 nv]`` (``[nv]`` with ``velocity_only``) by part."""
    b, off = (6 if floating_base else 0), (0 if velocity_only else nv)
    out = {"joint rate": off + np.arange(b, nv)}
    if not velocity_only:
        out = {"joint angle": np.arange(b, nv), **out}
    if b:
        base = {"base velocity": off + np.arange(0, 3), "base rate": off + np.arange(3, 6)}
        if not velocity_only:
            base = {"base position": np.arange(0, 3), "base orientation": np.arange(3, 6), **base}
        out = {**base, **out}
    return out


def cumulative(rollout_fn, params, test, spec, horizon, starts, scales, keys):
    """Cumulative RMSE per key (windows whose rollout left the floating-point range dropped),
    each part's share of the squared error and its RMS over the horizon (normalised units)."""
    vec = rollout.rollout_error_vectors(rollout_fn, params, test, spec, horizon, starts, scales,
                                        keys)  # [S, N, H, D]
    errs = rollout.per_horizon_rmse(vec)  # [S, N, H]
    ok = np.isfinite(errs).all(-1)  # [S, N]
    sq = np.where(ok[..., None, None], vec, 0.0) ** 2
    parts = groups(spec.nv, spec.floating_base)
    share = {g: float(sq[..., idx].sum() / sq.sum()) for g, idx in parts.items()}
    n = max(int(ok.sum()), 1) * vec.shape[2]  # kept rollouts x horizon
    rms = {g: float(np.sqrt(sq[..., idx].sum() / (n * len(idx)))) for g, idx in parts.items()}
    return [float(e[f].sum(-1).mean()) for e, f in zip(errs, ok)], share, rms


def per_part_rms(err: np.ndarray, nv: int, floating_base: bool) -> dict[str, float]:
    return {g: float(np.sqrt(np.mean(err[:, idx] ** 2)))
            for g, idx in groups(nv, floating_base, velocity_only=True).items()}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", required=True, help="dataset folder (stride data)")
    ap.add_argument("--runs", required=True, help="comma-separated run folders")
    ap.add_argument("--horizon", type=int, default=30)
    ap.add_argument("--windows", type=int, default=256)
    ap.add_argument("--samples", type=int, default=8)
    ap.add_argument("--steps", type=int, default=2000, help="transitions for the one-period errors")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="")
    a = ap.parse_args(argv)
    ds = dataset.load(a.data)
    spec = models.spec_from_meta(ds.meta)
    fb, nv = spec.floating_base, spec.nv
    test, train = ds.split("test"), ds.split("train")
    starts = rollout.windows(test["valid"], a.horizon, a.windows, a.seed)
    scales = rollout.observation_scales(train, spec, a.horizon)
    key = jax.random.key(a.seed)
    v = test["valid"][:, :-1] & test["valid"][:, 1:]
    ex = {k: jnp.asarray(test[k][:, :-1][v][:a.steps], jnp.float32)
          for k in ("q", "qd", "ctrl", "qdd", "tau")}
    qd_next = np.asarray(test["qd"][:, 1:][v][:a.steps])
    qd_std = train["qd"][train["valid"]].std(0) + 1e-9
    qdd_std = train["qdd"][train["valid"]].std(0) + 1e-9
    ctrl_dt = float(ds.meta["ctrl_dt"])
    period = (qd_next - np.asarray(ex["qd"])) / ctrl_dt
    data_gap = {"period-average acceleration rms": per_part_rms(period, nv, fb),
                "instantaneous qacc rms": per_part_rms(np.asarray(ex["qdd"]), nv, fb),
                "their difference rms": per_part_rms(period - np.asarray(ex["qdd"]), nv, fb)}
    print("data: " + "; ".join(f"{k}: " + ", ".join(f"{g} {x:.1f}" for g, x in d.items())
                               for k, d in data_gap.items()), flush=True)
    rows = []
    for run in [pathlib.Path(r) for r in a.runs.split(",") if r]:
        model, params = checkpoint.load(run)
        t0 = time.time()
        _, qd1 = jax.jit(jax.vmap(lambda q, qd, u: model.step(params, q, qd, u, None)))(
            ex["q"], ex["qd"], ex["ctrl"])
        one = per_part_rms((np.asarray(qd1) - qd_next) / qd_std, nv, fb)
        inst = None
        if model.acceleration is not None:
            acc = jax.jit(jax.vmap(lambda q, qd, t: model.acceleration(params, q, qd, t, None)))(
                ex["q"], ex["qd"], ex["tau"])
            inst = per_part_rms((np.asarray(acc) - np.asarray(ex["qdd"])) / qdd_std, nv, fb)
        for latents in (("step", "central") if model.stochastic else ("step",)):
            fn = lambda p, q, qd, u, k, latents=latents: model.rollout(p, q, qd, u, k, None,
                                                                        latents)
            n = a.samples if model.stochastic and latents == "step" else 1
            keys = jax.vmap(lambda s: jax.random.fold_in(key, s))(np.arange(n))
            got, share, rms = cumulative(fn, params, test, spec, a.horizon, starts, scales, keys)
            row = dict(run=str(run), model=model.name, latents=latents if model.stochastic else None,
                       state=float(np.mean(got)), spread=float(np.std(got)), samples=n,
                       share=share, rollout_rms=rms, one_period_qd_error=one,
                       instantaneous_qdd_error=inst)
            rows.append(row)
            print(f"{run.name:>16} {row['latents'] or '-':>8}: cumulative {a.horizon}-step RMSE "
                  f"{row['state']:.3f} (+- {row['spread']:.3f} over {n} draws, "
                  f"{time.time() - t0:.0f} s); RMS over the horizon by part: "
                  + ", ".join(f"{g} {x:.3f}" for g, x in rms.items()), flush=True)
        print(f"{'':>16} one-period velocity error (qd stds): "
              + ", ".join(f"{g} {x:.3f}" for g, x in one.items())
              + ("" if inst is None else "; instantaneous qacc error (qacc stds): "
                 + ", ".join(f"{g} {x:.3f}" for g, x in inst.items())), flush=True)
    out = dict(command="python " + " ".join(map(shlex.quote, [sys.argv[0], *(argv or sys.argv[1:])])),
               code=code_version(), data=a.data, data_meta={k: ds.meta[k] for k in
                                                            ("robot", "ctrl_dt", "n_substeps")},
               windows=len(starts), data_gap=data_gap, rows=rows)
    if a.out:
        atomic_write_text(a.out, json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main()
