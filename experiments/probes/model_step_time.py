"""Wall time of one jitted, vmapped model step (the planner's inner loop) per model, on this
machine: Go1, a batch of rollouts, integrating once per control step, networks at
initialisation; median of 50 calls, and the number of operations in the compiled step.

    python experiments/probes/model_step_time.py --hidden 64 --batch 128
"""

import argparse
import dataclasses
import time

import stride_jax
import jax
import jax.numpy as jnp
import numpy as np

import mppi_hlo_ops  # experiments/, beside this script
from stride_jax.jobs import bench_mppi as bench
from stride_jax.dynamics import models, stride
from stride_jax.train.setup import model_config


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--robot", default="go1")
    p.add_argument("--models", default="stride,delan,onn")
    p.add_argument("--hidden", type=int, default=64)
    p.add_argument("--depth", type=int, default=3)
    p.add_argument("--batch", type=int, default=128)
    p.add_argument("--shared-lnn", action="store_true", help="one network for L and V")
    a = p.parse_args()
    sm, meta, spec, act = bench._robot(a.robot)
    act = dataclasses.replace(act, dt=act.dt * act.n_substeps, n_substeps=1)
    B = a.batch
    for name in a.models.split(","):
        cfg = model_config(name, meta, a.hidden, a.depth, 0, a.shared_lnn)
        model = models.make(name, spec, act, cfg, stride.Scales())
        params = model.init(jax.random.key(0))
        f = jax.jit(jax.vmap(lambda q, qd, u, k: model.step(params, q, qd, u, k)))
        args = (jnp.tile(jnp.asarray(sm.info.qpos0), (B, 1)), 0.1 * jnp.ones((B, spec.nv)),
                jnp.zeros((B, len(act.dof))), jax.random.split(jax.random.key(0), B))
        n_ops = sum(mppi_hlo_ops.entry_ops(f.lower(*args).compile().as_text())[0].values())
        jax.block_until_ready(f(*args))
        times = []
        for _ in range(50):
            t0 = time.perf_counter()
            jax.block_until_ready(f(*args))
            times.append(time.perf_counter() - t0)
        print(f"{a.robot} {name} {a.hidden} x {a.depth}, batch {B}: "
              f"{1e3 * np.median(times):.3f} ms per model step, {n_ops} operations in its "
              "compiled HLO", flush=True)


if __name__ == "__main__":
    stride_jax.set_xla_flags()  # before JAX starts: small CPUs deadlock without
    main()
