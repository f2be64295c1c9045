"""Merge closed-loop runs (folders with ``closed_loop.json``, or JSON files of rows) into one
table, traces and plots: ``python experiments/closed_loop_merge.py PART... --out DIR --title T``
(``stride_jax.jobs.closed_loop.merge``); ``--onto MERGED.json`` appends to an earlier
merge, keeping its rows and their notes."""

import argparse

from stride_jax.jobs import closed_loop

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("parts", nargs="+")
    ap.add_argument("--out", required=True)
    ap.add_argument("--title", default="")
    ap.add_argument("--onto", default=None,
                    help="a merged closed_loop.json to append the parts to (its rows and notes kept)")
    a = ap.parse_args()
    rows = closed_loop.merge(a.parts, a.out, a.title, a.onto)
    print(f"{len(rows)} rows -> {a.out}/closed_loop.{{json,md}}")
