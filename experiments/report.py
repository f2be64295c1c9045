"""results/REPORT.md: the paper's claims, its numbers, ours and computed verdicts.

    python experiments/report.py                      # reads results/, writes results/REPORT.md
    python experiments/report.py --results R --out R/REPORT.md

Reads only result files (Table I's results/table1/<robot>/table.json, required; reproduce summaries,
MPPI benchmarks, closed-loop runs and the gap benchmark when present); see
``stride_paper.report``.
"""

from __future__ import annotations

import argparse
import pathlib
import sys

import stride_jax

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))  # stride_paper, if not installed
from stride_paper import report  # noqa: E402


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--results", default="results", help="results folder")
    p.add_argument("--out", default="", help="report path (default: <results>/REPORT.md)")
    args = p.parse_args(argv)
    rep = report.write(args.results, args.out or None)
    for i, r in enumerate(rep["rows"], 1):
        print(f"{i:2d}. {r.verdict:>14}: {r.claim}")
    print(f"wrote {rep['path']}")
    return rep


if __name__ == "__main__":
    stride_jax.set_xla_flags()  # before JAX starts: small CPUs deadlock without
    main()
