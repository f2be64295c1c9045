"""The fused network kernels (``stride_jax.dynamics.fused``) against XLA, pass by pass.

For a batch of ``--samples`` rows at the planner's sizes (Go1: the one-network Lagrangian prior
21 -> 166 outputs, the flow's vector field with its 58-wide context, ``--hidden`` x ``--depth``),
prints each pass's median time in XLA (the vmapped Flax network, differentiated by JAX) and as
one fused kernel, and the largest difference between the two. On a CPU the fused path is the
same batched maths in plain JAX (no kernel), so the numbers only mean something on a GPU:

    python experiments/probes/fused_kernels.py --samples 1024 --hidden 256
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp

import stride_jax
from stride_jax.dynamics import flow, fused, fused_pallas, mlp
from stride_jax.timing import median_time


def median_ms(f, *args, repeats: int = 50) -> float:
    return 1e3 * median_time(lambda: jax.block_until_ready(f(*args)), repeats)


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--samples", type=int, default=1024)
    p.add_argument("--hidden", type=int, default=256)
    p.add_argument("--depth", type=int, default=3)
    p.add_argument("--nfe", type=int, default=2)
    p.add_argument("--variants", default="64,16,4,2,float32",
                   help="kernel layouts to time, separated by ';': 'tile,rows,warps,stages,dtype' "
                        "(weight-tile columns, samples per program, warps, pipelining depth, "
                        "the products' input type)")
    p.add_argument("--loop", type=int, default=30, help="passes per timed call (in one jit)")
    a = p.parse_args()
    net = mlp.MLPConfig(a.hidden, a.depth)
    n_in, n_out, nv, n_ctx = 21, 166, 18, 58  # Go1
    keys = jax.random.split(jax.random.key(0), 8)
    init, apply = mlp.mlp(net, n_out)
    params = init(keys[0], n_in)
    x, t = (jax.random.normal(k, (a.samples, n_in)) for k in keys[1:3])
    g = jax.random.normal(keys[3], (a.samples, n_out))
    fcfg = flow.FlowConfig(net=net, nfe=a.nfe)
    # a trained-looking field: the last layer starts at zero
    fparams = jax.tree.map(lambda w: w + 0.05 * jax.random.normal(keys[4], w.shape),
                           flow.flow_init(keys[5], nv, n_ctx, fcfg))
    z0 = jax.random.normal(keys[6], (a.samples, nv))
    c = jax.random.normal(keys[7], (a.samples, n_ctx))
    def looped(f):
        """``--loop`` passes in one call (a planner's horizon), on shifted inputs."""
        def run(*args):
            shifts = jnp.arange(a.loop, dtype=jnp.float32) * 1e-3
            return jax.lax.map(lambda s: f(*[u + s for u in args]), shifts)
        return jax.jit(run)

    passes = {
        "jvp (forward + tangent)": (
            jax.vmap(lambda x, t: jax.jvp(lambda x: apply(params, x), (x,), (t,))),
            lambda dt: jax.vmap(lambda x, t: fused.jvp(params, x, t, dt)), (x, t)),
        "vjp (forward + transposed)": (
            jax.vmap(lambda x, g: jax.vjp(lambda x: apply(params, x), x)[1](g)[0]),
            lambda dt: jax.vmap(lambda x, g: fused.vjp(params, x, g, dt)), (x, g)),
        f"flow sample (NFE {a.nfe})": (
            jax.vmap(lambda z, c: flow.integrate(fparams, z, c, fcfg)),
            lambda dt: jax.vmap(lambda z, c: fused.flow_euler(fparams, z, c, a.nfe,
                                                              fcfg.time_features, dt)),
            (z0, c)),
    }
    print(f"{jax.devices()[0].device_kind}, K={a.samples}, {a.hidden} x {a.depth}, "
          f"us per pass ({a.loop} passes per call)")
    variants = [v.split(",") for v in a.variants.split(";")]
    print(f"{'pass':28s} {'XLA':>7s} " + " ".join(f"{','.join(v):>9s}" for v in variants)
          + f" {'max |diff|':>11s} {'max |ref|':>10s}")
    us = lambda f, args: 1e3 * median_ms(looped(f), *args) / a.loop
    for name, (ref, fast, args) in passes.items():
        print(f"{name:28s} {us(ref, args):7.1f}", end="", flush=True)
        r, diff = jax.jit(ref)(*args), 0.0
        for tile, rows, warps, stages, dtype in variants:
            layout = map(int, (tile, rows, warps, stages))
            fused_pallas.CHUNK, fused_pallas.ROWS, fused_pallas.WARPS, fused_pallas.STAGES = layout
            print(f" {us(fast(jnp.dtype(dtype)), args):9.1f}", end="", flush=True)
            f = jax.jit(fast(jnp.dtype(dtype)))(*args)
            diff = max([diff] + [float(jnp.max(jnp.abs(u - v))) for u, v in
                                 zip(jax.tree.leaves(r), jax.tree.leaves(f))])
        scale = max(float(jnp.max(jnp.abs(u))) for u in jax.tree.leaves(r))
        print(f" {diff:11.2e} {scale:10.2e}", flush=True)


if __name__ == "__main__":
    stride_jax.set_xla_flags()  # before JAX starts: small CPUs deadlock without
    main()
