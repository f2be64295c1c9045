"""Two runs of a gap benchmark, row by row: which verdicts a code change moved.

    python experiments/gap_bench_compare.py results/gap_bench_go1_independent_cases \\
        results/gap_bench_go1_independent_rerun/cases --out results/gap_bench_go1_independent_rerun/compare

Each folder holds a benchmark's finished rows (``<case>-<clean|noisy>.json``, as ``stride gap
bench-independent`` writes them in ``<name>_cases/``). Every row of the second run is set
beside the first run's row of the same file: its verdict, the effects named, the confidence,
whether the scorer counts it right, the best fit's values and the row's seconds. A row counts as
moved where any of verdict, named, confident or right differs. Writes ``OUT.md`` and ``OUT.json``.
"""

from __future__ import annotations

import argparse
import json
import pathlib

from stride_jax import io

KEYS = ("verdict", "named", "confident", "correct")


def _row(path: pathlib.Path) -> dict:
    data = json.loads(path.read_text())
    if "row" not in data:
        raise SystemExit(f"{path}: not a benchmark row (no 'row')")
    return dict(data["row"], code=data.get("code"))


def compare(before: pathlib.Path, after: pathlib.Path) -> dict:
    """The rows of ``after`` beside ``before``'s of the same case file."""
    for d in (before, after):
        if not d.is_dir():
            raise SystemExit(f"{d}: no such folder of benchmark rows")
    files = sorted(after.glob("*.json"))
    if not files:
        raise SystemExit(f"{after}: no rows (*.json)")
    rows = []
    for f in files:
        if not (before / f.name).is_file():
            raise SystemExit(f"{before / f.name}: the first run has no row for {f.name}")
        a, b = _row(before / f.name), _row(f)
        rows.append(dict(case=f.stem, planted=b.get("planted"),
                         moved=any(a.get(k) != b.get(k) for k in KEYS),
                         before={k: a.get(k) for k in KEYS + ("seconds", "code")}
                         | {"best": (a.get("best") or {}).get("params")},
                         after={k: b.get(k) for k in KEYS + ("seconds", "code")}
                         | {"best": (b.get("best") or {}).get("params")}))
    return dict(before=str(before), after=str(after), rows=rows,
                moved=sum(r["moved"] for r in rows), compared=len(rows),
                right_before=sum(bool(r["before"]["correct"]) for r in rows),
                right_after=sum(bool(r["after"]["correct"]) for r in rows))


def _cell(side: dict) -> str:
    named = "+".join(side["named"] or []) or "-"
    best = ", ".join(f"{k} {v}" for k, v in (side["best"] or {}).items())
    return (f"{side['verdict']}: {named}{' (confident)' if side['confident'] else ''}"
            f"{'' if side['correct'] else ', wrong'}; best {best or '-'}")


def markdown(res: dict, command: str) -> str:
    codes = lambda side: ", ".join(sorted({str(r[side]["code"]) for r in res["rows"]}))
    lines = ["# Gap benchmark rows, before and after", "", f"Command: `{command}`", "",
             f"Before: `{res['before']}` (code {codes('before')}); after: `{res['after']}` (code "
             f"{codes('after')}). {res['compared']} rows compared, **{res['moved']} moved** (verdict, "
             f"effects named, confidence or right / wrong); right {res['right_before']} -> "
             f"{res['right_after']} of them.", "",
             "| case | planted | moved | before | after | seconds before -> after |",
             "|---|---|---|---|---|---:|"]
    for r in res["rows"]:
        lines.append(f"| {r['case']} | {r['planted']} | {'**yes**' if r['moved'] else 'no'} | "
                     f"{_cell(r['before'])} | {_cell(r['after'])} | "
                     f"{r['before']['seconds'] or 0:.0f} -> {r['after']['seconds'] or 0:.0f} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("before", help="folder of the first run's rows")
    ap.add_argument("after", help="folder of the second run's rows (each compared with the first's)")
    ap.add_argument("--out", required=True, help="path stem: writes STEM.md and STEM.json")
    a = ap.parse_args(argv)
    res = compare(pathlib.Path(a.before), pathlib.Path(a.after))
    command = f"python experiments/gap_bench_compare.py {a.before} {a.after} --out {a.out}"
    stem = io.write_table(a.out, dict(command=command, **res), markdown(res, command))
    print(f"{res['compared']} rows compared, {res['moved']} moved -> {stem}.{{md,json}}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
