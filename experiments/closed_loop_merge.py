"""Merge closed-loop runs (folders with ``closed_loop.json``, or JSON files of rows) into one
table, traces and plots: ``python experiments/closed_loop_merge.py PART... --out DIR --title T``
(``stride_jax.jobs.closed_loop.merge``); ``--onto MERGED.json`` appends to an earlier
merge, keeping its rows and their notes."""

import argparse

from stride_jax.jobs import closed_loop

if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("parts", nargs="*", help="run folders or JSON files of rows (none: only "
                                             "--onto's table, e.g. with a new --headline)")
    ap.add_argument("--out", required=True)
    ap.add_argument("--title", default="")
    ap.add_argument("--onto", default=None,
                    help="a merged closed_loop.json to append the parts to (its rows and notes kept)")
    ap.add_argument("--headline", default=None,
                    help="comma-separated parts holding the current planner's rows (the report's "
                         "closed-loop claims read those alone); PART:MODEL+MODEL takes only "
                         "those models' rows of the part (e.g. se_changes:policy)")
    a = ap.parse_args()
    if not a.parts and not a.onto:
        ap.error("give parts to merge, or --onto a merged table")
    rows = closed_loop.merge(a.parts, a.out, a.title, a.onto,
                             a.headline.split(",") if a.headline else None)
    print(f"{len(rows)} rows -> {a.out}/closed_loop.{{json,md}}")
