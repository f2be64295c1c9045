"""Steady training rates of finished runs from their ``metrics.csv`` (issue 20): steps per second
from the second validation row to the last, so the first chunk's compilation is left out and
validation, checkpoints and the loop's own work are in. Runs trained side by side (``stride train
--seeds``: folders ``<out>-s<seed>``) are grouped by ``<out>`` and their seed-steps/s summed.

    python experiments/probes/train_e2e_rates.py RUN_DIR...   # e.g. results/throughput/train_seeds/e2e_s73/*/runs/*
"""

from __future__ import annotations

import collections
import csv
import pathlib
import re
import sys


def rate(run: pathlib.Path) -> float:
    rows = list(csv.DictReader(open(run / "metrics.csv")))
    if len(rows) < 3:
        raise SystemExit(f"{run}: {len(rows)} validation rows; need at least 3 for a steady rate")
    steps, times = [int(r["step"]) for r in rows], [float(r["time"]) for r in rows]
    return (steps[-1] - steps[1]) / (times[-1] - times[1])


def main(argv: list[str]) -> None:
    groups = collections.defaultdict(list)
    for arg in argv:
        run = pathlib.Path(arg)
        groups[re.sub(r"-s\d+$", "", str(run))].append(rate(run))
    print("| runs | side by side | steps/s each | seed-steps/s |\n|---|---:|---:|---:|")
    for name, rates in groups.items():
        print(f"| {name} | {len(rates)} | {', '.join(f'{r:.0f}' for r in rates)} | {sum(rates):.0f} |")


if __name__ == "__main__":
    main(sys.argv[1:])
