"""Does a model's validation loss pick the trained seed that plans best? Per robot, scenario and
model kind of a merged closed-loop table's headline: each trained seed's mean velocity RMSE
(``stride_paper.seeds.seed_means``: its planner draws that stayed up) beside the seed the
training's own held-out loss would choose (``best_val`` of the run's ``summary.json``), the mean
over seeds (what issue 19's targets read) and the best seed (known only after planning).

    python experiments/seed_selection.py \\
        go1=results/closed_loop_go1_gpu/closed_loop.json:results/models/go1_walk_ppo_go1_slope_slope20_tw1_tf0.25_com \\
        g1=results/closed_loop_g1_gpu/closed_loop.json:results/models/g1_walk_ppo_g1_slope_slope15_tw1_tf0.25 \\
        --out results/closed_loop_seed_selection

``--model-error ROBOT:SCENARIO=REPORT.json`` (repeatable) adds, per kind, how the seeds' one-period
model error along the policy's own episode (``experiments/scenario_model_error.py`` run on the
same models) orders them against their planning error.

``ROBOT=TABLE:MODELS``: a row's run folder (its ``run`` field, e.g. ``fm/slope/stride-s1``, a
copy carried to the GPU) is looked up by its name in ``MODELS``. The losses of different kinds
are in different units (STRIDE's includes its flow-matching term): seeds are compared within a
kind only. Writes ``OUT.md`` and ``OUT.json``; the targets keep the mean over seeds.
"""

from __future__ import annotations

import argparse
import collections
import json
import pathlib
import sys

import numpy as np
from scipy import stats

from stride_jax import io
from stride_paper.seeds import headline_picks, in_headline, kind_and_seed, seed_means

KINDS = ("stride", "delan", "onn")


def validation_losses(rows: list[dict], models: pathlib.Path) -> dict[tuple[str, int], float]:
    """``(kind, seed) -> best_val`` of each row's run folder found by name in ``models``."""
    out: dict[tuple[str, int], float] = {}
    names: dict[tuple[str, int], str] = {}
    for r in rows:
        key = kind_and_seed(r)
        name = pathlib.PurePath(str(r.get("run", ""))).name
        if key[0] not in KINDS:
            continue
        if key in names:
            if names[key] != name:  # one (kind, seed), two trainings: which loss is meant?
                raise ValueError(f"{key[0]} seed {key[1]} ran as {names[key]!r} and as {name!r} in the "
                                 f"headline: one validation score per trained seed is needed")
            continue
        names[key] = name
        summary = models / name / "summary.json"
        if not name or not summary.is_file():
            raise FileNotFoundError(f"row {r['model']!r} ({r['scenario']}): its run {r.get('run')!r} "
                                    f"has no summary.json under {models}")
        val = json.loads(summary.read_text()).get("best_val")
        if val is None or not np.isfinite(val):
            raise ValueError(f"{summary}: no finite best_val")
        out[key] = float(val)
    return out


def robot_selection(table: dict, models: pathlib.Path) -> dict:
    """Per scenario and kind: seeds' errors, the validation pick, mean and best; and the count
    of (scenario, kind) cells where the pick is the best seed."""
    picks = headline_picks(table)
    if not picks:
        raise ValueError("the table names no headline parts: nothing says which rows are the current planner")
    rows = [r for r in table["rows"] if in_headline(r, picks) and kind_and_seed(r)[0] in KINDS]
    val = validation_losses(rows, models)
    groups: dict[tuple[str, str], list[dict]] = {}
    for r in rows:
        groups.setdefault((r["scenario"], kind_and_seed(r)[0]), []).append(r)
    cells = []
    for sc in dict.fromkeys(r["scenario"] for r in rows):
        for kind in KINDS:
            means = seed_means(groups.get((sc, kind), []))
            if len(means) < 2:
                continue
            pick = min(means, key=lambda s: val[(kind, s)])
            best = min(means, key=means.get)
            cells.append(dict(scenario=sc, kind=kind, seeds={str(s): v for s, v in means.items()},
                              val={str(s): val[(kind, s)] for s in means}, pick=pick, best=best,
                              picked=means[pick], mean=float(np.mean(list(means.values()))),
                              best_value=means[best]))
    hits = {k: dict(best_picked=sum(c["pick"] == c["best"] for c in cells if c["kind"] == k),
                    of=sum(c["kind"] == k for c in cells)) for k in KINDS}
    return dict(cells=cells, hits=hits)


METRICS = ("bias_norm", "spread_norm", "joint_vel_rmse")


def model_errors(report: dict) -> dict[tuple[str, int], dict[str, float]]:
    """``(kind, seed) -> {metric: value}`` from ``experiments/scenario_model_error.py``'s JSON:
    each model's last phase (after its split: where the scenario's change acts), of the rows
    told the sensed gravity where the report has them (the closed loop's
    ``--planning.model-gravity``), else its plain rows; never the prior-alone rows."""
    rows = [r for r in report["rows"] if not r.get("prior_alone")]
    told = [r for r in rows if r.get("told_gravity")]
    out = {}
    for r in told or rows:
        phase = [k for k, v in r.items() if isinstance(v, dict) and "joint_vel_rmse" in v][-1]
        key = kind_and_seed(dict(model=str(r["model"]).split(" (")[0], run=r.get("run", "")))
        out[key] = {m: float(r[phase][m]) for m in METRICS} | {"phase": phase, "told_gravity": bool(told)}
    return out


def against_model_error(selection: dict, scenario: str, errors: dict) -> list[dict]:
    """Per kind in ``scenario``: each metric's rank correlation with the seeds' planning error
    and whether its lowest seed is the best-planning one."""
    cells = [c for c in selection["cells"] if c["scenario"] == scenario]
    if not cells:
        known = sorted({c["scenario"] for c in selection["cells"]})
        raise ValueError(f"no scenario {scenario!r} in the table's headline (it has {known})")
    out = []
    for c in cells:
        seeds = [int(s) for s in c["seeds"]]
        missing = [s for s in seeds if (c["kind"], s) not in errors]
        if missing:
            raise ValueError(f"{scenario}: the model-error report has no {c['kind']} seed(s) {missing}")
        plan = [c["seeds"][str(s)] for s in seeds]
        row = dict(scenario=scenario, kind=c["kind"], best=c["best"],
                   phase=errors[(c["kind"], seeds[0])]["phase"],
                   told_gravity=errors[(c["kind"], seeds[0])]["told_gravity"])
        for m in METRICS:
            vals = [errors[(c["kind"], s)][m] for s in seeds]
            lowest = seeds[int(np.argmin(vals))]
            row[m] = dict(per_seed={str(s): v for s, v in zip(seeds, vals)},
                          spearman=float(stats.spearmanr(vals, plan).statistic), lowest=lowest,
                          lowest_is_best=lowest == c["best"])
        out.append(row)
    return out


def markdown(results: dict[str, dict], command: str) -> str:
    lines = ["# Does the validation loss pick the seed that plans best? (issue 19)", "",
             f"Command: `{command}`", "",
             "Velocity RMSE (m/s) of each trained seed in the headline (mean of its planner draws "
             "that stayed up); `pick`: the seed with the lowest `best_val` of its training (the "
             "validation score that chose its best checkpoint; compared within a kind); `mean`: over seeds, what the targets read; "
             "`best`: the best seed, known only after planning. With three seeds a pick "
             "hits the best one by chance in 1 of 3 cells.", ""]
    for robot, res in results.items():
        lines += [f"## {robot}", "",
                  "| scenario | kind | per seed (validation loss) | pick | mean | best |",
                  "|---|---|---|---:|---:|---:|"]
        for c in res["cells"]:
            per = " / ".join(f"s{s}: {v:.4f} ({c['val'][s]:.3f})" for s, v in c["seeds"].items())
            mark = " (the best)" if c["pick"] == c["best"] else ""
            lines.append(f"| {c['scenario']} | {c['kind']} | {per} | s{c['pick']} {c['picked']:.4f}{mark} "
                         f"| {c['mean']:.4f} | s{c['best']} {c['best_value']:.4f} |")
        hit = ", ".join(f"{k} {h['best_picked']} of {h['of']}" for k, h in res["hits"].items())
        picked = "; ".join(f"{k}: " + ", ".join(f"s{s} in {n}" for s, n in sorted(collections.Counter(
            c["pick"] for c in res["cells"] if c["kind"] == k).items())) for k in res["hits"])
        lines += ["", f"- the validation pick is the best-planning seed: {hit}",
                  f"- the picks (one per kind, the same seed in every scenario where the same seeds "
                  f"ran): {picked}; cells of one pick are not independent draws", ""]
        if res.get("model_error"):
            lines += ["One-period model error along the policy's own episode in the scenario "
                      "(`experiments/scenario_model_error.py`; its last phase, told the gravity where "
                      "measured so): per metric the seeds' values, Spearman's rank correlation with "
                      "their planning error (1: the metric orders the seeds as planning does) and "
                      "whether its lowest seed plans best.", "",
                      "| scenario | kind | " + " | ".join(METRICS) + " |",
                      "|---|---|" + "---|" * len(METRICS)]
            for r in res["model_error"]:
                cells = [" / ".join(f"{v:.3f}" for v in r[m]["per_seed"].values())
                         + f" (rho {r[m]['spearman']:+.1f}{', lowest plans best' if r[m]['lowest_is_best'] else ''})"
                         for m in METRICS]
                lines.append(f"| {r['scenario']} | {r['kind']} | " + " | ".join(cells) + " |")
            me = res["model_error"]
            lines += [""] + [f"- {m}: orders the seeds as planning does (rho +1) in "
                             f"{sum(r[m]['spearman'] > 0.99 for r in me)} of {len(me)} cells, rho > 0 in "
                             f"{sum(r[m]['spearman'] > 0 for r in me)}; its lowest seed plans best in "
                             f"{sum(r[m]['lowest_is_best'] for r in me)} (chance: 1 in 6, 1 in 2, 1 in 3)"
                             for m in METRICS] + [""]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("tables", nargs="+", help="ROBOT=MERGED.json:MODELS_DIR")
    ap.add_argument("--model-error", action="append", default=[], metavar="ROBOT:SCENARIO=JSON",
                    help="a scenario_model_error.py report of the same models, compared per kind "
                         "with the seeds' planning error (repeatable)")
    ap.add_argument("--out", required=True, help="writes OUT.md and OUT.json")
    a = ap.parse_args(argv)
    results = {}
    for spec in a.tables:
        robot, eq, rest = spec.partition("=")
        path, colon, models = rest.rpartition(":")
        if not eq or not colon or not path or not models:
            ap.error(f"{spec!r}: expected ROBOT=MERGED.json:MODELS_DIR")
        if not pathlib.Path(path).is_file():
            ap.error(f"{path}: no such table")
        if not pathlib.Path(models).is_dir():
            ap.error(f"{models}: no such models folder")
        results[robot] = robot_selection(json.loads(pathlib.Path(path).read_text()), pathlib.Path(models))
    for spec in a.model_error:
        key, eq, path = spec.partition("=")
        robot, colon, scenario = key.partition(":")
        if not eq or not colon or robot not in results:
            ap.error(f"--model-error {spec!r}: expected ROBOT:SCENARIO=JSON, ROBOT one of {sorted(results)}")
        if not pathlib.Path(path).is_file():
            ap.error(f"--model-error {spec!r}: {path}: no such report")
        errors = model_errors(json.loads(pathlib.Path(path).read_text()))
        results[robot].setdefault("model_error", []).extend(
            against_model_error(results[robot], scenario, errors))
    command = "python experiments/seed_selection.py " + " ".join(sys.argv[1:] if argv is None else argv)
    stem = io.write_table(a.out, dict(command=command, robots=results), markdown(results, command))
    print(f"wrote {stem}.{{md,json}}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
