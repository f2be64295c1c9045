"""Open-loop accuracy of a stochastic model's central rollout against its random ones.

Each run (``stride train`` folder) rolls out ``--horizon`` control steps from ``--windows``
windows of the test split of ``--data`` (any dataset of the run's robot; the runs' own training
data need not be here): stochastic models once per ``--samples`` latent draws (``latents
"step"``, as Table I) and once with the residual's central sample at every step (``latents
"central"``, what ``MPPIConfig(latents="central")`` plans with); deterministic models once.
Prints and writes (``--out``, JSON) the cumulative normalised RMSE (Table I's state metric).

    python experiments/probes/central_latents.py --data /tmp/go1_walk_s11 \\
        --runs results/models/go1_walk/stride-s0,results/models/go1_walk/delan-s0,results/models/go1_walk/onn-s0
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time

import jax
import numpy as np

from stride_jax.dynamics import checkpoint, models
from stride_jax.eval import rollout
from stride_jax.io import atomic_write_text, code_version
from stride_jax.sim import dataset


def cumulative(rollout_fn, params, test, spec, horizon, starts, scales, keys) -> list[float]:
    """Cumulative RMSE per key (windows whose rollout left the floating-point range dropped)."""
    errs = rollout.per_horizon_rmse(rollout.rollout_error_vectors(
        rollout_fn, params, test, spec, horizon, starts, scales, keys))  # [S, N, H]
    return [float(e[np.isfinite(e).all(-1)].sum(-1).mean()) for e in errs]


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", required=True, help="dataset folder (stride data)")
    ap.add_argument("--runs", required=True, help="comma-separated run folders")
    ap.add_argument("--horizon", type=int, default=30)
    ap.add_argument("--windows", type=int, default=256)
    ap.add_argument("--samples", type=int, default=8)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="")
    a = ap.parse_args(argv)
    ds = dataset.load(a.data)
    spec = models.spec_from_meta(ds.meta)
    test, train = ds.split("test"), ds.split("train")
    starts = rollout.windows(test["valid"], a.horizon, a.windows, a.seed)
    scales = rollout.observation_scales(train, spec, a.horizon)
    key = jax.random.key(a.seed)
    rows = []
    for run in [pathlib.Path(r) for r in a.runs.split(",") if r]:
        model, params = checkpoint.load(run)
        t0 = time.time()
        for latents in (("step", "central") if model.stochastic else ("step",)):
            fn = lambda p, q, qd, u, k, latents=latents: model.rollout(p, q, qd, u, k, None,
                                                                        latents)
            n = a.samples if model.stochastic and latents == "step" else 1
            keys = jax.vmap(lambda s: jax.random.fold_in(key, s))(np.arange(n))
            got = cumulative(fn, params, test, spec, a.horizon, starts, scales, keys)
            row = dict(run=str(run), model=model.name, latents=latents if model.stochastic else None,
                       state=float(np.mean(got)), spread=float(np.std(got)), samples=n)
            rows.append(row)
            print(f"{run.name:>16} {row['latents'] or '-':>8}: cumulative {a.horizon}-step RMSE "
                  f"{row['state']:.3f} (+- {row['spread']:.3f} over {n} draws, "
                  f"{time.time() - t0:.0f} s)", flush=True)
    out = dict(command="python experiments/probes/central_latents.py " + " ".join(
        f"--{k} {v}" for k, v in vars(a).items() if v not in ("", None)),
        code=code_version(), data=a.data, windows=len(starts), rows=rows)
    if a.out:
        atomic_write_text(a.out, json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main()
