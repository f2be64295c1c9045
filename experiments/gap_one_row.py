"""Runs one row of the independent gap benchmark (one case, clean or noisy) and saves the scored
row and the whole diagnosis, to investigate a verdict without rerunning the benchmark.

    python experiments/gap_one_row.py --case 1 [--noisy] [--preset default] [--out /tmp/gap_rows]

Writes ``<out>/<case>-<clean|noisy>.json`` (``row``: as the benchmark scores it; ``diagnosis``:
the diagnosis's JSON-able result). Run it under the CPU lock: one Go1 row takes 2-8 minutes.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib
import tempfile
import time

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", type=int, required=True)
    ap.add_argument("--noisy", action="store_true")
    ap.add_argument("--preset", default="default")
    ap.add_argument("--out", default="/tmp/gap_rows")
    a = ap.parse_args()
    from stride_jax.gap import diagnose, logs, nominal
    from stride_jax.jobs import gap_bench_independent as bi
    from stride_jax.jobs import gap_bench_score as scoring

    cfg = bi.PRESETS[a.preset]
    t0 = time.time()
    sm = nominal.load(cfg.robot, "shipped")
    clean, logged, settings, form = bi.real_logs(cfg, a.case, a.noisy)
    with tempfile.TemporaryDirectory() as tmp:
        logs.write(tmp, sm, logged, notes=f"independent benchmark case {a.case}")
        _, trajs = logs.read(tmp, sm)
    dcfg = diagnose.PRESETS[cfg.diagnose]
    if cfg.pairs_of >= 0:
        dcfg = dataclasses.replace(dcfg, pairs_of=cfg.pairs_of)
    dcfg = dataclasses.replace(dcfg, progress=False)
    res = diagnose.diagnose(sm, trajs, dcfg)
    held = [t for t in clean if t.name in set(res["heldout"])]
    row = scoring.score(sm, bi.cases(cfg)[a.case], res, held, settings, form, dcfg.attribute_min)
    row |= {"noisy": a.noisy, "case": a.case, "row_seconds": time.time() - t0}
    out = pathlib.Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    keep = {k: v for k, v in res.items() if not k.startswith("_")}
    path = out / f"{a.case:02d}-{'noisy' if a.noisy else 'clean'}.json"
    path.write_text(json.dumps({"row": row, "diagnosis": keep}, indent=1, default=_js))
    print(f"{path}: {row['verdict']} {row['named']} confident={row['confident']} ratio={row.get('shrink_ratio')} "
          f"({row['row_seconds']:.0f} s; stages {res.get('stage_seconds')})")


def _js(x):
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, (np.floating, np.integer, np.bool_)):
        return x.item()
    return str(x)


if __name__ == "__main__":
    main()
