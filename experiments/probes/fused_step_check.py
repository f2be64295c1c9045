"""The whole-step kernel (``stride_jax/dynamics/fused_step.py``) against XLA on this machine's
default device: agreement of one model step over a batch of states (the step's acceleration),
and the time of one vmapped step and of a vmapped 30-step rollout for each kernel choice. Go1
(or ``--robot g1``) STRIDE, one network for L and V:

    python experiments/probes/fused_step_check.py [--run results/mppi_latency/planning_shared/stride-h64-shared]
        [--samples 1024] [--kernels xla,pallas-bf16,pallas-step,pallas-step-bf16]

Without ``--run`` the model is at initialisation with its weights perturbed (the flow's last
layer starts at zero). Prints as it goes.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np

import stride_jax
from stride_jax.jobs import bench_mppi as bench
from stride_jax import dynamics
from stride_jax.dynamics import fused_step, models, stride
from stride_jax.timing import median_time
from stride_jax.train.setup import model_config


def parse_blocks(text: str) -> dict:
    """``--block``: ``"4"`` (every loop) or ``"factor=4,backward=2"`` -> ``fused_step.BLOCK``."""
    loops = ("products", "gram", "factor", "backward")
    if text.isdigit():
        return dict.fromkeys(loops, int(text))
    out = {}
    for item in filter(None, text.split(",")):
        name, _, width = item.partition("=")
        if name not in loops or not width.isdigit() or int(width) < 1:
            raise SystemExit(f"--block {item!r}: want N or name=N with name one of {loops}")
        out[name] = int(width)
    return out


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--run", default="", help="a STRIDE run with shared_lnn (else: init)")
    p.add_argument("--robot", default="go1", help="go1 or g1 (the model at initialisation)")
    p.add_argument("--hidden", type=int, default=64)
    p.add_argument("--samples", type=int, default=1024)
    p.add_argument("--horizon", type=int, default=30)
    p.add_argument("--repeats", type=int, default=20)
    p.add_argument("--substeps", type=int, default=1,
                   help="model steps per control step, at-init models only (the bench's 1)")
    p.add_argument("--kernels", default="xla,pallas-bf16,pallas-step,pallas-step-bf16")
    p.add_argument("--skip", default="", help="parts of the step kernel to leave out, to time "
                   "the others (fused_step.SKIP: products, flow, solve; wrong results)")
    p.add_argument("--unroll", default="", help="the step kernel's loops to unroll "
                   "(fused_step.UNROLL: products, gram, factor, backward)")
    p.add_argument("--block", default="", help="columns per iteration of the step kernel's "
                   "loops: N for all, or name=N,... (fused_step.BLOCK: products, gram, factor, "
                   "backward; 1 where not given; empty: the library's default, 4 in every loop "
                   "since session 83; 1: the kernel before)")
    p.add_argument("--split", type=int, default=-1, choices=(-1, 0, 1),
                   help="the reduced system factorised in two halves (1) or whole (0); -1: "
                   "the library's default (fused_step.SPLIT, halves since session 84)")
    p.add_argument("--warps", type=int, default=0,
                   help="warps per program of the step kernel (0: fused_step.WARPS)")
    p.add_argument("--rows", type=int, default=0,
                   help="samples per program of the step kernel (0: fused_step.program_rows)")
    a = p.parse_args()
    fused_step.ROWS = a.rows or None
    if a.warps:
        fused_step.WARPS = a.warps
    fused_step.UNROLL = frozenset(x for x in a.unroll.split(",") if x)
    fused_step.SKIP = frozenset(x for x in a.skip.split(",") if x)
    if a.block:
        fused_step.BLOCK = parse_blocks(a.block)
    if a.split >= 0:
        fused_step.SPLIT = bool(a.split)
    sm, meta, spec, act = bench._robot(a.robot)
    if a.run:
        params = dynamics.load(a.run)[1]
        model_of = lambda kernel: dynamics.load(a.run, kernel=kernel)[0]
    else:
        act = dataclasses.replace(act, dt=act.dt * act.n_substeps / a.substeps,
                                  n_substeps=a.substeps)
        cfg = model_config("stride", meta, a.hidden, 3, 2, True)
        scales = stride.Scales()
        params = models.make("stride", spec, act, cfg, scales).init(jax.random.key(0))
        noise = lambda x, k: x + 0.05 * jax.random.normal(k, x.shape)
        leaves, tree = jax.tree.flatten(params)
        params = tree.unflatten([noise(x, jax.random.key(i)) for i, x in enumerate(leaves)])
        model_of = lambda kernel: models.make("stride", spec, act,
                                              dataclasses.replace(cfg, kernel=kernel), scales)
    K, H = a.samples, a.horizon
    rng = np.random.default_rng(0)
    q0 = np.asarray(sm.info.qpos0, np.float32)
    q = np.tile(q0, (K, 1)) + 0.05 * rng.standard_normal((K, q0.size)).astype(np.float32)
    q[:, 3:7] /= np.linalg.norm(q[:, 3:7], axis=1, keepdims=True)
    qd = (0.5 * rng.standard_normal((K, spec.nv))).astype(np.float32)
    nu = q0.size - 7  # every joint actuated (Go1, G1)
    ctrl = q[:, 7:] + 0.1 * rng.standard_normal((K, nu)).astype(np.float32)
    keys = jax.random.split(jax.random.key(1), K)
    ctrls = jnp.asarray(np.tile(ctrl[:, None], (1, H, 1)))
    print(f"{jax.devices()[0].device_kind}: {a.robot} STRIDE, K={K}, H={H}, "
          f"{fused_step.program_rows(K)} rows per program of the step kernel", flush=True)
    ref = None
    for kernel in a.kernels.split(","):
        model = model_of(kernel)
        step = jax.jit(jax.vmap(model.step, in_axes=(None, 0, 0, 0, 0)))
        out = jax.block_until_ready(step(params, q, qd, ctrl, keys))
        acc = (np.asarray(out[1]) - qd) / act.dt  # the step's acceleration
        if ref is None:
            ref = acc
        err = np.abs(acc - ref).max(axis=1) / (np.abs(ref).max(axis=1) + 1.0)
        one_ms = 1e3 * median_time(lambda: jax.block_until_ready(step(params, q, qd, ctrl, keys)),
                                   a.repeats)
        roll = jax.jit(jax.vmap(model.rollout, in_axes=(None, 0, 0, 0, 0)))
        t0 = time.perf_counter()
        jax.block_until_ready(roll(params, q, qd, ctrls, keys))
        compile_s = time.perf_counter() - t0
        ms = 1e3 * median_time(lambda: jax.block_until_ready(roll(params, q, qd, ctrls, keys)),
                               a.repeats)
        print(f"{kernel:18s} one step {one_ms:6.3f} ms; rollout {ms:7.3f} ms "
              f"({1e3 * ms / H:6.1f} us/step, compile {compile_s:.1f} s); acceleration vs "
              f"{a.kernels.split(',')[0]}: max rel {err.max():.2e}, median "
              f"{np.median(err):.2e}", flush=True)


if __name__ == "__main__":
    stride_jax.set_xla_flags()  # before JAX starts: small CPUs deadlock without
    main()
