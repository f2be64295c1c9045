"""Do the named effects' intervals cover the planted values on logs whose simulator differs from
the nominal model? Reads a folder of independent-benchmark rows (``stride gap bench-independent``'s
``<name>_cases/`` or ``experiments/gap_one_row.py``'s output) and, for every planted continuous
parameter the best hypothesis fitted (delays, fitted on a grid of simulation steps, are left out),
prints the estimate, its interval, whether it covers the planted value, and the error as a share
of the planted departure from the nominal value.

    python experiments/probes/interval_coverage_rows.py results/gap_bench_go1_independent_cases [--out FILE.md]
"""

from __future__ import annotations

import argparse
import json
import pathlib

import numpy as np

from stride_jax.gap import effects
from stride_jax.io import atomic_write_text


def rows(folder: pathlib.Path) -> list[dict]:
    out = []
    for f in sorted(folder.glob("*.json")):
        row = json.loads(f.read_text()).get("row")
        if not row or row["kind"] not in ("single", "pair"):
            continue
        best = row["best"]
        for name, truth in row["planted"].items():
            e = effects.ALL[name]
            if e.integer:
                continue
            est = best["params"].get(name)
            for i, t in enumerate(np.atleast_1d(truth)):
                nominal = float(np.atleast_1d(e.nominal)[i])
                item = {"row": f.stem, "effect": name + (f"[{i}]" if len(np.atleast_1d(truth)) > 1 else ""),
                        "truth": float(t), "fitted": est is not None}
                if est is not None:
                    lo, hi = best["lo"][name][i], best["hi"][name][i]
                    dep = abs(float(t) - nominal)
                    item |= {"estimate": est[i], "lo": lo, "hi": hi, "covered": bool(lo <= t <= hi),
                             "error_of_departure": abs(est[i] - t) / dep if dep > 0 else None,
                             "half_width_of_departure": (hi - lo) / 2 / dep if dep > 0 else None}
                out.append(item)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder")
    ap.add_argument("--out", default="")
    a = ap.parse_args()
    items = rows(pathlib.Path(a.folder))
    L = [f"# Intervals against the planted values: `{a.folder}`", "",
         f"Command: `python experiments/probes/interval_coverage_rows.py {a.folder}"
         + (f" --out {a.out}`" if a.out else "`"), "",
         "| row | parameter | planted | estimate | 90% interval | covered | error / planted departure | "
         "half width / departure |", "|---|---|---:|---:|---|---|---:|---:|"]
    for it in items:
        if not it["fitted"]:
            L.append(f"| {it['row']} | {it['effect']} | {it['truth']:.4g} | not fitted | | no | | |")
            continue
        f = lambda v: "-" if v is None else f"{v:.1%}"
        L.append(f"| {it['row']} | {it['effect']} | {it['truth']:.4g} | {it['estimate']:.4g} | "
                 f"[{it['lo']:.4g}, {it['hi']:.4g}] | {'yes' if it['covered'] else 'no'} | "
                 f"{f(it['error_of_departure'])} | {f(it['half_width_of_departure'])} |")
    fitted = [it for it in items if it["fitted"]]
    errs = [it["error_of_departure"] for it in fitted if it["error_of_departure"] is not None]
    hw = [it["half_width_of_departure"] for it in fitted if it["half_width_of_departure"] is not None]
    L += ["", f"Covered: {sum(it['covered'] for it in fitted)} of {len(fitted)} fitted parameters "
          f"({len(items) - len(fitted)} planted parameters not in the best hypothesis). Error as a share of the "
          f"planted departure from nominal: median {np.median(errs):.1%}, 90th percentile "
          f"{np.percentile(errs, 90):.1%}, max {max(errs):.1%}; the intervals' half widths: median "
          f"{np.median(hw):.1%}."]
    text = "\n".join(L) + "\n"
    print(text)
    if a.out:
        atomic_write_text(pathlib.Path(a.out), text)


if __name__ == "__main__":
    main()
