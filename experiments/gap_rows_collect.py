"""Collects rows of the independent gap benchmark run one by one (``experiments/gap_one_row.py``,
``experiments/gap_rows_parallel.sh``: on several machines, in several calls) into the benchmark's
own row folder, and writes its tables once every row is there -- the same files ``stride gap
bench-independent`` writes.

    python experiments/gap_rows_collect.py --out results/gap_bench_go1_independent_s74 \\
        /tmp/dev1/rows=6ee85b6 /tmp/dev2/rows=af526e2 ... [--command "how the rows were made"]

Each ``FOLDER=CODE`` holds ``<case>-<clean|noisy>.json`` rows made at code ``CODE`` (a plain
``FOLDER``: the code each row file records, as ``gap_one_row.py`` now writes it); a row in a
later folder replaces one of an earlier folder. The rows are stored as the benchmark stores
them (``<out>/<name>_cases/``, without the diagnosis), so ``gap_bench_compare.py`` and a resumed
``stride gap bench-independent --out <out>`` read them.
"""

from __future__ import annotations

import argparse
import json
import pathlib

from stride_jax.jobs import gap_bench as bench
from stride_jax.jobs import gap_bench_independent as bi


def collect(items: list[str], out: str, preset: str = "default", command: str = "", log=print) -> dict:
    """Stores the rows of ``items`` (``FOLDER=CODE`` or ``FOLDER``, in order) in ``out``'s row
    folder and writes the tables if every row is there; returns :func:`gap_bench_independent.run`'s
    result (``complete`` False with the counts otherwise)."""
    cfg = bi.PRESETS[preset]
    dest = bench.rows_dir(cfg, out)
    for item in items:
        folder, _, code = item.partition("=")
        files = sorted(pathlib.Path(folder).glob("[0-9]*-*.json"))
        if not files:
            raise SystemExit(f"{folder}: no rows (NN-clean.json / NN-noisy.json)")
        for f in files:
            data = json.loads(f.read_text())
            if not (code or data.get("code")):
                raise SystemExit(f"{f}: records no code; give its folder as {folder}=CODE")
            bench.save_row(dest, cfg, data["row"], code or data["code"])
        log(f"{folder}: {len(files)} rows" + (f" at {code}" if code else ""))
    return bi.run(cfg, out, command=command, log=log, minutes=0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folders", nargs="+", help="FOLDER=CODE or FOLDER, in order (later rows replace earlier ones)")
    ap.add_argument("--out", required=True)
    ap.add_argument("--preset", default="default")
    ap.add_argument("--command", default="")
    a = ap.parse_args()
    res = collect(a.folders, a.out, a.preset, a.command)
    print("complete" if res.get("complete", True) else f"incomplete: {res['done']} of {res['total']} rows")


if __name__ == "__main__":
    main()
