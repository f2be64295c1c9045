"""Whether a scenario's tracking error goes with the robot's forward speed: per trained model
(kind and seed) of a merged closed-loop table's headline rows, its mean forward velocity over the
episode (``mean_vx``, the closed loop's row) and its velocity RMSE, each the mean over its planner
draws, and the rank correlation of the two over the learned models (Spearman's; the policy and
oracle rows listed beside, not counted).

    python experiments/speed_vs_error.py results/closed_loop_go1_gpu/closed_loop.json \\
        --scenarios slope,tilt --out results/planning_diagnosis/speed_vs_error_go1

A correlation near 1 says the models that lose are those that plan the robot faster than its
command (an overshoot the planner's observer does not take out), near -1 slower.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import shlex
import sys

import numpy as np

from stride_jax.io import write_table
from stride_paper.seeds import headline_picks, in_headline, kind_and_seed

LEARNED = ("stride", "delan", "onn")


def speed_and_error(table: dict, scenario: str) -> dict:
    """``{"models": [{kind, seed, draws, mean_vx, vel_rmse}], "spearman": rho or None}`` of the
    headline rows of ``scenario`` (rows without ``mean_vx`` left out)."""
    from scipy import stats

    picks = headline_picks(table)
    if not picks:
        raise ValueError("the table names no headline parts: nothing says which rows are current")
    groups: dict[tuple[str, int], list[dict]] = {}
    for r in table["rows"]:
        if r["scenario"] == scenario and in_headline(r, picks) and r.get("mean_vx") is not None:
            groups.setdefault(kind_and_seed(r), []).append(r)
    if not groups:
        raise ValueError(f"no headline rows of scenario {scenario!r} with a mean_vx")
    models = [dict(kind=k, seed=s, draws=len(rs),
                   mean_vx=float(np.mean([r["mean_vx"] for r in rs])),
                   vel_rmse=float(np.mean([r["vel_rmse"] for r in rs])))
              for (k, s), rs in sorted(groups.items())]
    learned = [m for m in models if m["kind"] in LEARNED]
    rho = None
    if len(learned) >= 3:
        rho = float(stats.spearmanr([m["mean_vx"] for m in learned],
                                    [m["vel_rmse"] for m in learned]).statistic)
    return dict(models=models, spearman=rho if rho is None or np.isfinite(rho) else None)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("table", help="a merged closed_loop.json with a headline")
    ap.add_argument("--scenarios", required=True, help="comma-separated")
    ap.add_argument("--out", required=True, help="path stem: writes OUT.md and OUT.json")
    a = ap.parse_args(argv)
    path = pathlib.Path(a.table)
    if not path.is_file():
        raise SystemExit(f"{a.table}: no such file")
    table = json.loads(path.read_text())
    result = {sc: speed_and_error(table, sc) for sc in a.scenarios.split(",") if sc}
    command = "python " + " ".join(map(shlex.quote, [sys.argv[0], *(argv or sys.argv[1:])]))
    lines = [f"# Forward speed against tracking error ({path})", "", f"Command: `{command}`", "",
             "Per trained model: the mean over its planner draws of the episode's mean forward "
             "velocity (m/s) and of its velocity RMSE (m/s); Spearman's rank correlation of the "
             "two over the learned models (STRIDE, DeLaN + MLP, ONN).", ""]
    for sc, res in result.items():
        rho = res["spearman"]
        lines += [f"## {sc}: Spearman {'-' if rho is None else f'{rho:+.2f}'}", "",
                  "| model | seed | draws | mean vx | vel RMSE |", "|---|---:|---:|---:|---:|"]
        lines += [f"| {m['kind']} | {m['seed']} | {m['draws']} | {m['mean_vx']:.3f} | "
                  f"{m['vel_rmse']:.4f} |" for m in res["models"]]
        lines.append("")
    write_table(pathlib.Path(a.out), dict(command=command, scenarios=result), "\n".join(lines))
    print(f"wrote {a.out}.{{md,json}}")
    return result


if __name__ == "__main__":
    main()
