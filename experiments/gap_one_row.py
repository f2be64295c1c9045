"""Runs one row of the independent gap benchmark (one case, clean or noisy) and saves the scored
row and the whole diagnosis, to investigate a verdict without rerunning the benchmark.

    python experiments/gap_one_row.py --case 1 [--noisy] [--preset default] [--out /tmp/gap_rows]

Writes ``<out>/<case>-<clean|noisy>.json`` (``row``: as the benchmark scores it; ``diagnosis``:
the diagnosis's JSON-able result). Run it under the CPU lock: one Go1 row takes 2-8 minutes.
"""

from __future__ import annotations

import argparse
import json
import pathlib


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", type=int, required=True)
    ap.add_argument("--noisy", action="store_true")
    ap.add_argument("--preset", default="default")
    ap.add_argument("--out", default="/tmp/gap_rows")
    a = ap.parse_args()
    from stride_jax.jobs import gap_bench_independent as bi
    from stride_jax.io import atomic_write_text
    from stride_jax.jobs.gap_report import json_default

    row, res = bi.diagnose_case(bi.PRESETS[a.preset], a.case, a.noisy)
    out = pathlib.Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    keep = {k: v for k, v in res.items() if not k.startswith("_")}
    path = out / f"{a.case:02d}-{'noisy' if a.noisy else 'clean'}.json"
    atomic_write_text(path, json.dumps({"row": row, "diagnosis": keep}, indent=1, default=json_default))
    print(f"{path}: {row['verdict']} {row['named']} confident={row['confident']} ratio={row.get('shrink_ratio')} "
          f"({row['row_seconds']:.0f} s; stages {res.get('stage_seconds')})")


if __name__ == "__main__":
    main()
