"""What bfloat16 products (``kernel="xla-bf16"``) cost a trained model in accuracy.

For each run: the cumulative 30-step state error (``stride eval``'s metric, one sample per key)
of the model with float32 products and with bfloat16 products, both against the logged future,
and the error of the bfloat16 rollout against the float32 one (same keys, so the same latents:
only the rounding differs), on the run's test split.

    python experiments/probes/bf16_accuracy.py --runs 'runs/go1/*' --out /tmp/bf16.json
"""

from __future__ import annotations

import argparse
import glob
import json
import pathlib

import jax
import jax.numpy as jnp
import numpy as np

from stride_jax import io
from stride_jax import dynamics
from stride_jax.dynamics import models
from stride_jax.eval import rollout, runs as runs_lib


def compare(run: pathlib.Path, horizon: int, windows: int, samples: int, seed: int) -> dict:
    run_cfg = json.loads((run / "config.json").read_text())
    ds = runs_lib.load_dataset(run_cfg["dataset"])
    spec = models.spec_from_meta(ds.meta)
    test, train = ds.split("test"), ds.split("train")
    starts = rollout.windows(test["valid"], horizon, windows, seed)
    scales = rollout.observation_scales(train, spec, horizon)
    out = {"run": str(run)}
    preds = {}
    for kernel in ("xla", "xla-bf16"):
        model, params = dynamics.load(run, kernel=kernel)
        keys = jax.vmap(lambda s: jax.random.fold_in(jax.random.key(seed), s))(
            jnp.arange(samples if model.stochastic else 1))
        q, qd, ctrl = rollout.window_arrays(test, starts, horizon)

        def one(q0, qd0, u, k):
            return model.rollout(params, q0, qd0, u, k)

        roll = jax.jit(jax.vmap(lambda k: jax.vmap(one)(q[:, 0], qd[:, 0], ctrl,
                                                         jax.random.split(k, len(q)))))
        preds[kernel] = roll(keys)  # ([S, N, H, nq], [S, N, H, nv])
        errs = jax.vmap(jax.vmap(lambda a, b, qr, qdr: rollout.normalised_errors(
            a, b, qr, qdr, scales, spec.floating_base), in_axes=(0, 0, 0, 0)), in_axes=(0, 0, None, None))(
            *preds[kernel], q[:, 1:], qd[:, 1:])
        out[kernel] = rollout.cumulative_rmse(rollout.per_horizon_rmse(np.asarray(errs)))
        out["model"] = model.name
    gap = jax.vmap(jax.vmap(lambda a, b, c, d: rollout.normalised_errors(a, b, c, d, scales, spec.floating_base)))(
        *preds["xla-bf16"], *preds["xla"])
    out["bf16_vs_f32"] = rollout.cumulative_rmse(rollout.per_horizon_rmse(np.asarray(gap)))
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", required=True, help="comma-separated run folders or globs")
    ap.add_argument("--horizon", type=int, default=30)
    ap.add_argument("--windows", type=int, default=256)
    ap.add_argument("--samples", type=int, default=4)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="")
    a = ap.parse_args(argv)
    runs = sorted({pathlib.Path(p) for part in a.runs.split(",") for p in glob.glob(part)
                   if (pathlib.Path(p) / "model.json").is_file()})
    rows = [compare(r, a.horizon, a.windows, a.samples, a.seed) for r in runs]
    print(f"{'run':40s} {'float32':>9s} {'bfloat16':>9s} {'bf16 vs f32':>12s}")
    for r in rows:
        print(f"{r['run'][-40:]:40s} {r['xla']:9.3f} {r['xla-bf16']:9.3f} {r['bf16_vs_f32']:12.3f}")
    if a.out:
        io.atomic_write_text(pathlib.Path(a.out), json.dumps({"argv": argv, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
