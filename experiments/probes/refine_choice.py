"""Which effect the calibration's refinement holds fixed, with and without the joint groups of
its best joint effects in its screen (``CalibrateConfig.refine_finer``), on each row of the
independent gap benchmark: a row whose held effect is the same both ways diagnoses exactly as
before, so only the rows listed as changed need running again.

    python experiments/probes/refine_choice.py --out /tmp/refine_choice.jsonl [--cases "0 1 2"]
        [--noise clean,noisy]

Appends one JSON line per row (resumable: rows already in ``--out`` are skipped). Each row runs
the diagnosis's first calibration (40-190 s a row on the benchmark's 6 x 4 s Go1 logs, one
thread) and two screens.

    python experiments/probes/refine_choice.py --summary /tmp/refine_choice.jsonl [--margin 0.1]

writes the rows as a markdown table, the held effect under ``--margin``
(``CalibrateConfig.refine_finer_margin``) derived from the recorded screens: the library's
effects are screened the same way with and without the joint groups, so the best library row
and the best group row decide it exactly.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib
import sys
import time

sys.path.insert(0, str(pathlib.Path(__file__).parent))
from calibration_with_effect import row_data  # noqa: E402

from stride_jax.gap import calibrate  # noqa: E402
from stride_jax.jobs import gap_bench_independent as bi  # noqa: E402


def held_under(row: dict, margin: float) -> dict:
    """The effect the refinement holds under ``margin`` (:func:`calibrate.held_choice`), from the
    probe's recorded screens: the screen with groups' top rows and the best library row."""
    screens = row["screens"]
    top = next((v for k, v in screens.items() if k != "0"), screens["0"])["top"]
    lib = screens["0"]["top"][:1]
    rows = sorted(top + [r for r in lib if r not in top], key=lambda r: r["loss"])
    pick, _ = calibrate.held_choice(rows, {r["effect"] for r in rows if "@" in r["effect"]}, margin)
    # a group held passed min_gain where the no-margin screen held it; the library row as before
    return row["held_now"] if pick and "@" in pick["effect"] else row["held_before"]


def summary(path: str, margin: float) -> None:
    rows = [json.loads(x) for x in pathlib.Path(path).read_text().splitlines()]
    rows.sort(key=lambda r: (r["case"], r["noisy"]))
    fmt = lambda h: ", ".join(f"{n} {v:.4g}" for n, v in h.items()) or "none"
    print(f"Command: `python experiments/probes/refine_choice.py --summary {path} --margin {margin:g}`\n")
    print("| row | planted | held without groups | held with groups | changed | best group in the top 3 (its training loss / the best library effect's) |")
    print("|---|---|---|---|---|---:|")
    for r in rows:
        now = held_under(r, margin)
        lib = r["screens"]["0"]["top"][0] if r["screens"]["0"]["top"] else None
        grp = next((t for k, v in r["screens"].items() if k != "0" for t in v["top"] if "@" in t["effect"]), None)
        ratio = f"{grp['effect']} {grp['loss'] / lib['loss']:.3f}" if grp and lib and lib["loss"] > 0 else "-"
        print(f"| {r['case']:02d}-{'noisy' if r['noisy'] else 'clean'} | {r['planted'] or '{}'} | {fmt(r['held_before'])} "
              f"| {fmt(now)} | {'**yes**' if sorted(now) != sorted(r['held_before']) else 'no'} | {ratio} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--summary", default="", help="a probe's JSON lines: print them as a table instead")
    ap.add_argument("--margin", type=float, default=0.1, help="with --summary: refine_finer_margin")
    ap.add_argument("--out", default="")
    ap.add_argument("--preset", default="default", help="the benchmark's preset (its cases)")
    ap.add_argument("--cases", default="", help="space-separated case indices (empty: all)")
    ap.add_argument("--noise", default="clean,noisy")
    a = ap.parse_args()
    if a.summary:
        return summary(a.summary, a.margin)
    if not a.out:
        ap.error("--out is required without --summary")
    bcfg = bi.PRESETS[a.preset]
    out = pathlib.Path(a.out)
    done = set()
    if out.exists():
        done = {(r["case"], r["noisy"]) for r in map(json.loads, out.read_text().splitlines())}
    cases = [int(c) for c in a.cases.split()] or range(len(bi.cases(bcfg)))
    for case in cases:
        for noisy in [n == "noisy" for n in a.noise.split(",")]:
            if (case, noisy) in done:
                continue
            t0 = time.time()
            p, cfg, _ = row_data(bcfg, case, noisy)
            cal = calibrate.calibrate(p.sm, p.train_k, p.test_k, p.scale, cfg.calibrate, log=lambda s: None)
            held = {}
            for k in (0, cfg.calibrate.refine_finer):
                c = dataclasses.replace(cfg.calibrate, refine_finer=k)
                pick, rec = calibrate.screen(cal.model, p.train_k, p.scale, c, cfg.fit.grid)
                held[k] = {"held": {n: v[0] for n, v in pick.items()}, "top": rec["screen"][:3],
                           "replays": rec["replays"]}
            old, new = held[0]["held"], held[cfg.calibrate.refine_finer]["held"]
            row = {"case": case, "noisy": noisy, "planted": bi.cases(bcfg)[case]["planted"], "held_before": old,
                   "held_now": new, "changed": sorted(old) != sorted(new), "screens": held,
                   "seconds": time.time() - t0}
            with out.open("a") as f:
                f.write(json.dumps(row) + "\n")
            print(f"case {case:2d} {'noisy' if noisy else 'clean'} planted {row['planted']}: held {old} -> {new}"
                  + ("  <- changed" if row["changed"] else "") + f" ({row['seconds']:.0f} s)", flush=True)


if __name__ == "__main__":
    main()
