"""Velocity RMSE per scenario as grouped bars, from a merged closed-loop table
(``closed_loop.json``): one bar per planner, each picked by model and, in order of preference,
parts (``stride_jax.jobs.closed_loop.select``); falls hatched and timed.

    python experiments/closed_loop_bars.py results/closed_loop_g1_gpu/closed_loop.json \\
        --scenarios walk,push,soft --out tw1.png \\
        --planner "policy=policy@walk,walk_push" --planner "STRIDE=stride@tw1_walk,tw1_push"

``--planner LABEL=MODEL[@PART,PART...]``: the rows of MODEL (a merged row's name before any
``@part``), each scenario from the first listed part that has it (no parts: any).
"""

from __future__ import annotations

import argparse
import json
import pathlib

from stride_jax.jobs import closed_loop


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("table", help="a merged closed_loop.json")
    ap.add_argument("--planner", action="append", required=True)
    ap.add_argument("--scenarios", required=True, help="comma-separated, in plot order")
    ap.add_argument("--out", required=True)
    ap.add_argument("--title", default="")
    ap.add_argument("--ylim", type=float, default=None,
                    help="clip the bars here (clipped ones carry their value)")
    ap.add_argument("--label", action="append", default=[],
                    help="SCENARIO=TEXT: the scenario's tick label")
    a = ap.parse_args(argv)
    path = pathlib.Path(a.table)
    if not path.is_file():
        raise SystemExit(f"{path}: no such closed-loop table")
    rows = json.loads(path.read_text())["rows"]
    scenarios = [s for s in a.scenarios.split(",") if s]
    planners = {}
    for spec in a.planner:
        try:
            label, model, parts = closed_loop.parse_pick(spec)
        except ValueError as e:
            raise SystemExit(str(e)) from None
        got = {sc: r for sc, r in closed_loop.select(rows, model, parts).items() if sc in scenarios}
        if not got:
            raise SystemExit(f"--planner {spec!r}: no row of model {model!r}"
                             + (f" in parts {', '.join(parts)}" if parts else "")
                             + f" for scenarios {', '.join(scenarios)}")
        planners[label] = got
    labels = dict(spec.partition("=")[::2] for spec in a.label)
    closed_loop.bars(planners, scenarios, a.out, a.title, labels=labels, ylim=a.ylim)
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
