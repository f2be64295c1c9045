"""Kernel-launching operations in one compiled MPPI planning step, by kind (GPU latency study).

The planner's rollouts are unrolled (no loops), so the ENTRY computation of the optimised HLO
lists everything one planning step launches: fusions, library calls (cuBLAS, cuSOLVER) and the
command buffers (CUDA graphs) XLA grouped some of them into. Usage:

    python experiments/probes/mppi_hlo_ops.py --robot go1 --model stride --samples 1024 --horizon 30
    python experiments/probes/mppi_hlo_ops.py --shared-lnn --hidden 64 --kernel pallas-bf16 --horizon 4
"""

from __future__ import annotations

import argparse
import collections
import re

import jax

import stride_jax
from stride_jax.jobs import bench_mppi as bench


def entry_ops(hlo: str) -> tuple[collections.Counter, collections.Counter]:
    """Opcode counts of the ENTRY computation's instructions (custom calls by target), and the
    fusions and calls counted by the JAX operation they came from (the last part of their
    ``op_name``: ``dot_general``, ``cholesky``, ``threefry2x32`` ...)."""
    entry = hlo[hlo.index("ENTRY"):]
    body = entry[:entry.index("\n}")]
    counts, sources = collections.Counter(), collections.Counter()
    for line in body.splitlines()[1:]:
        name = re.search(r'op_name="([^"]*)"', line)
        if name and re.search(r"= (?:\([^=]*?\)|\S+) (fusion|custom-call|call)\(", line):
            sources[name.group(1).rsplit("/", 1)[-1]] += 1
        m = re.search(r"= (?:\([^=]*?\)|\S+) ([a-z][a-z0-9\-]*)\(", line)
        if not m:
            continue
        op = m.group(1)
        if op == "custom-call":
            target = re.search(r'custom_call_target="([^"]+)"', line)
            op = f"custom-call:{target.group(1) if target else '?'}"
        elif op == "call" and "command_buffer" in line:
            op = "command-buffer"
        counts[op] += 1
    return counts, sources


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--robot", default="go1")
    p.add_argument("--model", default="stride")
    p.add_argument("--samples", type=int, default=1024)
    p.add_argument("--horizon", type=int, default=30)
    p.add_argument("--shared-lnn", action="store_true", help="one network for L and V")
    p.add_argument("--hidden", type=int, default=256)
    p.add_argument("--kernel", default="xla", help="xla, pallas or pallas-bf16")
    a = p.parse_args()
    b = bench.setup(a.robot, a.model, a.samples, a.horizon,  # the GPU preset's step, unrolled
                    bench.BenchConfig(substeps=1, unroll=0, shared_lnn=a.shared_lnn,
                                      hidden=a.hidden, kernel=a.kernel))
    compiled = jax.jit(b.step).lower(b.state, b.q0, b.qd0).compile()
    counts, sources = entry_ops(compiled.as_text())
    print(f"{a.robot} {a.model} K={a.samples} H={a.horizon} on {jax.devices()[0].device_kind}: "
          f"{sum(counts.values())} ENTRY instructions, "
          f"{sum(counts.values()) / a.horizon:.1f} per horizon step")
    for op, n in counts.most_common():
        print(f"  {op:40s} {n:6d}  ({n / a.horizon:.1f} per step)")
    print("fusions and calls by the JAX operation they came from:")
    for op, n in sources.most_common(30):
        print(f"  {op:40s} {n:6d}  ({n / a.horizon:.1f} per step)")


if __name__ == "__main__":
    stride_jax.set_xla_flags()  # before JAX starts: small CPUs deadlock without
    main()
