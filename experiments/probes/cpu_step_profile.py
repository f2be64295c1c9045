"""Where a jitted MPPI planning step spends its time on this CPU: JAX's profiler over a few
steps of ``stride bench-mppi``'s planner (networks at initialisation, integrating once per
control step), the XLA operations' time summed by kind (``ynn_fusion.12`` -> ``ynn_fusion``)
and by name, per planning step and summed over the host devices.

    STRIDE_HOST_DEVICES=auto python experiments/probes/cpu_step_profile.py --out results/mppi_latency/cpu_profile

Writes ``profile_<robot>_<model>.md`` (and ``.json``) under ``--out``; prints the table.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import gzip
import json
import pathlib
import re
import sys
import tempfile
import time

import stride_jax

# the profiler's own and Python's events, not XLA operations
NOT_OPS = ("ThunkExecutor", "while", "$", "Pjit", "Common", "Wait", "cpp_", "shard_args",
           "end: ", "[", "DevicePut", "Rendezvous wait")


def profile(robot: str, model: str, K: int, H: int, steps: int) -> dict:
    import jax

    from stride_jax.jobs import bench_mppi as bench

    cfg = dataclasses.replace(bench.PRESETS["target"], substeps=1)
    b = bench.setup(robot, model, K, H, cfg)
    step = jax.jit(b.step)
    args = (b.state, b.q0, b.qd0)
    for _ in range(5):  # compiled and warm
        jax.block_until_ready(step(*args))
    t = time.perf_counter()
    for _ in range(steps):
        jax.block_until_ready(step(*args))
    wall_ms = (time.perf_counter() - t) / steps * 1e3
    with tempfile.TemporaryDirectory() as tmp:
        jax.profiler.start_trace(tmp, create_perfetto_trace=True)
        for _ in range(steps):
            jax.block_until_ready(step(*args))
        jax.profiler.stop_trace()
        trace = sorted(pathlib.Path(tmp).rglob("*.trace.json.gz"))[-1]
        events = json.load(gzip.open(trace))
    events = events["traceEvents"] if isinstance(events, dict) else events
    by_name, calls = collections.Counter(), collections.Counter()
    for e in events:
        if e.get("ph") == "X" and not e["name"].startswith(NOT_OPS):
            by_name[e["name"]] += e.get("dur", 0) / 1e3 / steps
            calls[e["name"]] += 1 / steps
    by_kind = collections.Counter()
    for name, ms in by_name.items():
        by_kind[re.sub(r"\.\d+$", "", name)] += ms
    return dict(robot=robot, model=model, K=K, H=H, steps=steps, wall_ms=wall_ms,
                devices=len(jax.devices()), by_kind=dict(by_kind.most_common()),
                by_name={n: [ms, calls[n]] for n, ms in by_name.most_common(30)})


def table(r: dict, command: str) -> str:
    lines = [f"# {r['robot']} {r['model']}, K={r['K']}, H={r['H']}: where the planning step's "
             f"time goes", "", f"Command: `{command}`", "",
             f"Wall time {r['wall_ms']:.2f} ms per planning step (mean of {r['steps']}), "
             f"{r['devices']} host device(s); the operations' times below are summed over the "
             f"devices (each device runs its share side by side).", "",
             "| operation kind | ms per step (all devices) | share |", "|---|---:|---:|"]
    total = sum(r["by_kind"].values())
    lines += [f"| `{k}` | {ms:.2f} | {ms / total:.0%} |"
              for k, ms in list(r["by_kind"].items())[:20]]
    lines += ["", "| operation | ms per step | calls per step |", "|---|---:|---:|"]
    lines += [f"| `{n}` | {ms:.2f} | {c:.1f} |" for n, (ms, c) in r["by_name"].items()]
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    stride_jax.set_xla_flags()
    from stride_jax.io import atomic_write_text

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--robot", default="go1")
    p.add_argument("--model", default="stride")
    p.add_argument("--samples", type=int, default=128)
    p.add_argument("--horizon", type=int, default=16)
    p.add_argument("--steps", type=int, default=10)
    p.add_argument("--out", default="")
    a = p.parse_args(argv)
    r = profile(a.robot, a.model, a.samples, a.horizon, a.steps)
    text = table(r, "python experiments/probes/cpu_step_profile.py " + " ".join(
        sys.argv[1:] if argv is None else argv))
    print(text)
    if a.out:
        out = pathlib.Path(a.out)
        out.mkdir(parents=True, exist_ok=True)
        stem = f"profile_{a.robot}_{a.model}"
        atomic_write_text(out / f"{stem}.json", json.dumps(r, indent=1))
        atomic_write_text(out / f"{stem}.md", text)


if __name__ == "__main__":
    main()
