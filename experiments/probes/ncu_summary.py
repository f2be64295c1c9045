"""Sums an ``ncu --csv --page raw`` log of ``--steps`` identical steps (``ncu_train.sh``): kernels
per step, their summed duration, the busiest kernels by time with their compute (SM) and memory
throughput as % of peak, and the share of the summed time spent in kernels under 10 us.

    python experiments/probes/ncu_summary.py LOG.csv [--steps 2] [--top 12]
"""

from __future__ import annotations

import argparse
import collections
import csv
import re


SCALE_NS = {"nsecond": 1.0, "ns": 1.0, "usecond": 1e3, "us": 1e3, "msecond": 1e6, "ms": 1e6}


def rows(path: str) -> tuple[list[dict], dict]:
    """The kernel rows of ncu's raw CSV (its log lines dropped) and its units row."""
    lines = [ln for ln in open(path, errors="replace") if ln.startswith('"')]
    table = list(csv.DictReader(lines))
    units = next((r for r in table if not r.get("ID", "").isdigit()), {})
    return [r for r in table if r.get("ID", "").isdigit()], units


def _num(x: str) -> float:
    try:
        return float(x.replace(",", ""))
    except (AttributeError, ValueError):
        return float("nan")


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("log")
    p.add_argument("--steps", type=int, default=2)
    p.add_argument("--top", type=int, default=12)
    a = p.parse_args()
    table, units = rows(a.log)
    if not table:
        print(f"no kernel rows in {a.log}")
        return
    dur = "gpu__time_duration.sum"
    sm = "sm__throughput.avg.pct_of_peak_sustained_elapsed"
    mem = "gpu__compute_memory_throughput.avg.pct_of_peak_sustained_elapsed"
    scale = SCALE_NS.get(units.get(dur, "nsecond").strip(), 1.0)
    ns = [scale * _num(r[dur]) for r in table]
    total = sum(ns) / a.steps
    small = sum(t for t in ns if t < 10_000) / a.steps
    print(f"{len(table) / a.steps:.0f} kernels per step, {total / 1e3:.1f} us of kernel time per "
          f"step; kernels under 10 us: {small / 1e3:.1f} us ({100 * small / total:.0f}%)")
    groups = collections.defaultdict(list)
    for r, t in zip(table, ns):
        name = re.sub(r"_\d+$", "", r.get("Kernel Name", "?"))[:60]
        groups[name].append((t, _num(r[sm]), _num(r[mem])))
    ranked = sorted(groups.items(), key=lambda kv: -sum(x[0] for x in kv[1]))
    print(f"{'kernel':60s} {'calls':>6s} {'us/step':>8s} {'SM %':>6s} {'mem %':>6s}")
    for name, xs in ranked[:a.top]:
        t = sum(x[0] for x in xs)
        w = lambda i: sum(x[0] * x[i] for x in xs) / t  # time-weighted
        print(f"{name:60s} {len(xs) / a.steps:6.0f} {t / a.steps / 1e3:8.1f} {w(1):6.1f} {w(2):6.1f}")
    t_all = sum(ns)
    print(f"time-weighted over all kernels: SM {sum(t * _num(r[sm]) for r, t in zip(table, ns)) / t_all:.1f}%, "
          f"memory {sum(t * _num(r[mem]) for r, t in zip(table, ns)) / t_all:.1f}%")


if __name__ == "__main__":
    main()
