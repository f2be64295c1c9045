"""One training step of a structured model against its FLOP and memory floors on this machine's
default device (issue 20, item 4): the optimiser step of ``stride train`` (``loop.scan_steps``: a
minibatch drawn, the per-example loss vmapped, its gradient, Adam) on synthetic examples of the
robot's shapes, timed as ``stride train`` runs it (``--chunk`` steps per jitted scan).

    python experiments/probes/train_step_floor.py [--robot go1] [--hidden 256] [--batch 1024]
        [--model stride] [--seeds 1] [--out results/throughput/train_step]

Floors: XLA's own count of the step's FLOPs and bytes accessed (``cost_analysis`` of one step,
compiled unrolled: XLA counts a loop body once), over the measured matmul peak (a large float32
product, as ``stride bench-mppi`` measures it) and the measured copy bandwidth. ``--cuda-profile``
brackets ``--profile-steps`` timed steps with ``cudaProfilerStart/Stop`` so that ``ncu
--profile-from-start off`` sees only those kernels (``experiments/probes/ncu_train.sh``).
Writes ``train_step.json`` to ``--out`` and prints a line per measurement.
"""

from __future__ import annotations

import argparse
import ctypes
import ctypes.util
import glob
import json
import os
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np

import stride_jax
from stride_jax.dynamics import models, stride
from stride_jax.jobs import bench_mppi as bench
from stride_jax.timing import median_time, peak_flops
from stride_jax.train.loop import optimizer, scan_steps
from stride_jax.train.setup import model_config

from mppi_hlo_ops import entry_ops  # this folder's (the script's own directory is on sys.path)


def examples(spec, q0: np.ndarray, n: int, feet: int, seed: int = 0) -> dict:
    """``n`` examples with the training set's keys and shapes (values of a plausible scale)."""
    rng = np.random.default_rng(seed)
    f = lambda *s: rng.standard_normal(s).astype(np.float32)
    q = np.tile(q0.astype(np.float32), (n, 1)) + 0.05 * f(n, q0.size)
    if spec.floating_base:
        q[:, 3:7] /= np.linalg.norm(q[:, 3:7], axis=1, keepdims=True)
    stance = (rng.random((n, feet, 1, 1)) < 0.5).astype(np.float32)
    jac = (f(n, feet, 3, spec.nv) * stance).reshape(n, feet * 3, spec.nv)
    nu = spec.nv - 6 if spec.floating_base else spec.nv
    return {"q": q, "qd": 0.5 * f(n, spec.nv), "tau": 5.0 * f(n, spec.nv),
            "qdd": 5.0 * f(n, spec.nv), "ctrl": f(n, nu), "contact_jac": jac}


def copy_bandwidth(mb: int = 512, repeats: int = 5) -> float:
    """Measured bytes/s of a large device copy (read + write)."""
    x = jnp.ones((mb * 2 ** 20 // 4,), jnp.float32)
    f = jax.jit(lambda a: a * 1.0001)
    f(x).block_until_ready()
    best = min(median_time(lambda: f(x).block_until_ready(), 1) for _ in range(repeats))
    return 2 * x.nbytes / best


def _cost(compiled) -> dict:
    cost = compiled.cost_analysis()
    cost = cost[0] if isinstance(cost, (list, tuple)) else cost
    return dict(cost or {})


def kernel_profile(fn, calls: int, top: int = 15) -> dict:
    """The device's kernels over ``calls`` calls of ``fn`` (JAX's profiler, CUPTI on a GPU): per
    call, their count and summed time, and the ``top`` kernels by time. Empty off a GPU."""
    import tempfile

    from jax.profiler import ProfileData

    with tempfile.TemporaryDirectory() as tmp:
        with jax.profiler.trace(tmp):
            for _ in range(calls):
                jax.block_until_ready(fn())
        paths = glob.glob(os.path.join(tmp, "**", "*.xplane.pb"), recursive=True)
        data = ProfileData.from_file(paths[0])
        planes = [p for p in data.planes if p.name.startswith("/device:GPU")]
        if not planes:
            return {"planes": [p.name for p in data.planes]}
        per_name, lines = {}, []
        for line in planes[0].lines:
            lines.append(line.name)
            if not line.name.startswith("Stream"):  # "XLA Ops"/"XLA Modules" repeat the kernels
                continue
            for ev in line.events:
                n, t = per_name.get(ev.name, (0, 0.0))
                per_name[ev.name] = (n + 1, t + ev.duration_ns)
    total = sum(t for _, t in per_name.values())
    ranked = sorted(per_name.items(), key=lambda kv: -kv[1][1])
    return {"lines": lines, "kernels_per_call": sum(n for n, _ in per_name.values()) / calls,
            "kernel_us_per_call": total / calls / 1e3,
            "top": [{"name": k[:80], "calls_per_call": n / calls, "us_per_call": t / calls / 1e3}
                    for k, (n, t) in ranked[:top]]}


def _cudart():
    """``libcudart`` of the CUDA wheels JAX uses (for cudaProfilerStart/Stop), or None."""
    try:
        import nvidia  # the pip CUDA packages' namespace
        roots = list(nvidia.__path__)
    except ImportError:
        roots = []
    for root in roots:
        for path in glob.glob(os.path.join(root, "cuda_runtime", "lib", "libcudart.so*")):
            return ctypes.CDLL(path)
    # an image whose JAX links the system CUDA (the lent machines'): the toolkit's runtime
    name = ctypes.util.find_library("cudart")
    paths = ([name] if name else []) + sorted(glob.glob("/usr/local/cuda/lib64/libcudart.so*"))
    return ctypes.CDLL(paths[0]) if paths else None


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--robot", default="go1")
    p.add_argument("--model", default="stride")
    p.add_argument("--hidden", type=int, default=256)
    p.add_argument("--depth", type=int, default=3)
    p.add_argument("--batch", type=int, default=1024)
    p.add_argument("--chunk", type=int, default=100, help="steps per jitted scan (timed)")
    p.add_argument("--examples", type=int, default=65536)
    p.add_argument("--shared-lnn", action="store_true")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--cuda-profile", action="store_true")
    p.add_argument("--profile-steps", type=int, default=2)
    p.add_argument("--seeds", type=int, default=1,
                   help="independent models trained side by side in one program (vmapped over their "
                        "parameters, optimiser states and draws): the throughput of many small trainings")
    p.add_argument("--trace", type=int, default=0,
                   help="single steps to trace with JAX's profiler (kernel times per step)")
    p.add_argument("--out", default="")
    a = p.parse_args()

    sm, meta, spec, act = bench._robot(a.robot)
    cfg = model_config(a.model, meta, a.hidden, a.depth, 0, a.shared_lnn)
    model = models.make(a.model, spec, act, cfg, stride.Scales())
    if a.seeds < 1:
        raise SystemExit(f"--seeds {a.seeds}: need at least 1")
    params = model.init(jax.random.key(0))
    feet = sm.nfeet or 1
    data = jax.device_put(examples(spec, np.asarray(sm.info.qpos0), a.examples, feet))
    opt = optimizer(1e-3, 10_000)
    opt_state = opt.init(params)

    def mean_loss(params, ex, key):
        keys = jax.random.split(key, len(ex["q"]))
        total, parts = jax.vmap(model.loss, in_axes=(None, 0, 0))(params, ex, keys)
        return jnp.mean(total), jax.tree.map(jnp.mean, parts)

    def steps(n):
        if a.seeds == 1:
            return jax.jit(lambda params, opt_state, start: scan_steps(
                mean_loss, opt, params, opt_state, data, jax.random.key(1), start, n, a.batch))
        keys = jax.random.split(jax.random.key(1), a.seeds)  # each model its own minibatches
        many = jax.vmap(lambda p_, s_, k_, start: scan_steps(mean_loss, opt, p_, s_, data, k_, start, n, a.batch),
                        in_axes=(0, 0, 0, None))
        return jax.jit(lambda params, opt_state, start: many(params, opt_state, keys, start))

    if a.seeds > 1:  # the models' own initialisations, stacked
        params = jax.vmap(model.init)(jax.random.split(jax.random.key(0), a.seeds))
        opt_state = jax.vmap(opt.init)(params)

    one = steps(1).lower(params, opt_state, 0).compile()  # one step, no loop: XLA counts it all
    cost = _cost(one)
    flops, nbytes = float(cost.get("flops", np.nan)), float(cost.get("bytes accessed", np.nan))
    run = steps(a.chunk)
    t0 = time.perf_counter()
    jax.block_until_ready(run(params, opt_state, 0))
    compile_s = time.perf_counter() - t0
    per_step = median_time(lambda: jax.block_until_ready(run(params, opt_state, 0)),
                           a.repeats) / a.chunk
    single = median_time(lambda: jax.block_until_ready(one(params, opt_state, 0)), a.repeats)
    peak32, peak16, bw = peak_flops(4096), peak_flops(4096, dtype="bfloat16"), copy_bandwidth()
    row = dict(device=jax.devices()[0].device_kind, robot=a.robot, model=a.model,
               hidden=a.hidden, depth=a.depth, batch=a.batch, shared_lnn=a.shared_lnn,
               chunk=a.chunk, seeds=a.seeds, step_ms=1e3 * per_step, one_step_call_ms=1e3 * single,
               examples_per_s=a.seeds * a.batch / per_step, compile_s=compile_s,
               flops_per_step=flops, bytes_per_step=nbytes, peak_tflops_f32=peak32 / 1e12,
               peak_tflops_bf16=peak16 / 1e12, copy_gbs=bw / 1e9,
               flop_floor_ms=1e3 * flops / peak32, memory_floor_ms=1e3 * nbytes / bw,
               xla_flags=os.environ.get("XLA_FLAGS", ""), jax=jax.__version__)
    counts, sources = entry_ops(one.as_text())  # one step unrolled: what it launches
    row["entry_ops"] = dict(counts.most_common())
    row["entry_sources"] = dict(sources.most_common(25))
    row["x_flop_floor"] = row["step_ms"] / row["flop_floor_ms"]
    row["x_memory_floor"] = row["step_ms"] / row["memory_floor_ms"]
    print(json.dumps({k: v for k, v in row.items() if k != "entry_sources"}), flush=True)
    if a.trace:
        row["kernels"] = kernel_profile(lambda: one(params, opt_state, 0), a.trace)
        print(json.dumps(row["kernels"]), flush=True)
    if a.cuda_profile:  # the kernels of a few single steps, for ncu --profile-from-start off
        lib = _cudart()
        if lib is None:
            raise SystemExit("no libcudart found under the nvidia packages")
        lib.cudaProfilerStart()
        for _ in range(a.profile_steps):
            jax.block_until_ready(one(params, opt_state, 0))
        lib.cudaProfilerStop()
    if a.out:
        out = pathlib.Path(a.out)
        out.mkdir(parents=True, exist_ok=True)
        name = f"train_step_{a.robot}_{a.model}_{a.hidden}x{a.depth}_b{a.batch}" + \
            (f"_seeds{a.seeds}" if a.seeds > 1 else "") + ".json"
        (out / name).write_text(json.dumps(row, indent=1) + "\n")


if __name__ == "__main__":
    stride_jax.set_xla_flags()  # before JAX starts: small CPUs deadlock without
    main()
