"""Runs one row of the independent gap benchmark (one case, clean or noisy) and saves the scored
row and the whole diagnosis, to investigate a verdict without rerunning the benchmark.

    python experiments/gap_one_row.py --case 1 [--noisy] [--preset default] [--out /tmp/gap_rows]
        [--no-step-cost]   # the calibration takes a finer time step at min_gain alone
        [--trajectories 12 --steps 400 --diagnose default]   # longer logs, another diagnosis preset

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
    ap.add_argument("--no-step-cost", action="store_true",
                    help="CalibrateConfig.step_cost off in the benchmark's diagnosis preset")
    ap.add_argument("--trajectories", type=int, default=0, help="per case (0: the preset's)")
    ap.add_argument("--steps", type=int, default=0, help="control steps per trajectory (0: the preset's)")
    ap.add_argument("--diagnose", default="", help="the diagnosis's preset (empty: the benchmark's)")
    a = ap.parse_args()
    import dataclasses

    from stride_jax.gap import diagnose
    from stride_jax.jobs import gap_bench_independent as bi
    from stride_jax.io import atomic_write_text, code_version
    from stride_jax.jobs.gap_report import json_default

    if a.preset not in bi.PRESETS or (a.diagnose and a.diagnose not in diagnose.PRESETS):
        raise SystemExit(f"--preset {a.preset!r} / --diagnose {a.diagnose!r}: the benchmark's presets are "
                         f"{sorted(bi.PRESETS)}, the diagnosis's {sorted(diagnose.PRESETS)}")
    cfg = bi.PRESETS[a.preset]
    cfg = dataclasses.replace(cfg, **{k: v for k, v in (("trajectories", a.trajectories), ("steps", a.steps),
                                                         ("diagnose", a.diagnose)) if v})
    if a.no_step_cost:  # the diagnosis preset is looked up by name: replace it for this process
        d = diagnose.PRESETS[cfg.diagnose]
        diagnose.PRESETS[cfg.diagnose] = dataclasses.replace(
            d, calibrate=dataclasses.replace(d.calibrate, step_cost=False))
    row, res = bi.diagnose_case(cfg, a.case, a.noisy)
    out = pathlib.Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    keep = {k: v for k, v in res.items() if not k.startswith("_")}
    path = out / f"{a.case:02d}-{'noisy' if a.noisy else 'clean'}.json"
    atomic_write_text(path, json.dumps({"code": code_version(), "row": row, "diagnosis": keep}, indent=1,
                                       default=json_default))
    print(f"{path}: {row['verdict']} {row['named']} confident={row['confident']} ratio={row.get('shrink_ratio')} "
          f"({row['row_seconds']:.0f} s; stages {res.get('stage_seconds')})")


if __name__ == "__main__":
    main()
