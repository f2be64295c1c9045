"""What the fused kernels' arithmetic does to a trained model's predictions: the open-loop
rollout error (Table I's cumulative 30-step state RMSE) of one run with its networks in XLA,
as fused float32 kernels and as fused kernels with bfloat16 products, on the same windows and
latents. On a CPU the kernels run in Pallas' interpreter, which computes their arithmetic
(bfloat16 rounding included) exactly as written:

    python experiments/probes/fused_accuracy.py --run results/mppi_latency/planning_shared/stride-h64-shared \\
        --data data/go1 --windows 64
"""

from __future__ import annotations

import argparse

import jax
import numpy as np

import stride_jax
from stride_jax import dynamics
from stride_jax.dynamics import fused, models
from stride_jax.eval import rollout
from stride_jax.sim import dataset


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--run", required=True, help="a `stride train` run folder")
    p.add_argument("--data", required=True, help="a dataset folder of the same robot")
    p.add_argument("--windows", type=int, default=64)
    p.add_argument("--horizon", type=int, default=30)
    p.add_argument("--samples", type=int, default=4, help="latent draws per window")
    a = p.parse_args()
    ds = dataset.load(a.data)
    test, train = ds.split("test"), ds.split("train")
    spec = models.spec_from_meta(ds.meta)
    errors = {}
    starts = rollout.windows(test["valid"], a.horizon, a.windows)
    scales = rollout.observation_scales(train, spec, a.horizon)
    keys = jax.random.split(jax.random.key(0), a.samples)
    for kernel in fused.KERNELS:
        model, params = dynamics.load(a.run, kernel=kernel)
        if kernel == "xla":
            errors[kernel] = rollout.rollout_errors(model.rollout, params, test, spec, a.horizon,
                                                    starts, scales, keys)
        else:
            with fused.interpret():
                errors[kernel] = rollout.rollout_errors(model.rollout, params, test, spec,
                                                        a.horizon, starts, scales, keys)
    ref = errors["xla"].sum(-1)  # [samples, windows] cumulative errors
    print(f"{a.run}: {len(starts)} windows x {a.samples} latents, H={a.horizon}")
    print(f"{'kernel':12s} {'state RMSE':>10s} {'max |change| per window':>24s}")
    for kernel, e in errors.items():
        cum = e.sum(-1)
        print(f"{kernel:12s} {cum.mean():10.4f} {np.abs(cum - ref).max():24.2e}")


if __name__ == "__main__":
    stride_jax.set_xla_flags()  # before JAX starts: small CPUs deadlock without
    main()
