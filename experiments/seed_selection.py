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

``--pick-by ROBOT=REPORT.json`` (repeatable) tries such a metric as a selection rule, measured where
a user could measure it before planning: on episodes outside the table (e.g. the policy's level
walk, ``scenario_model_error.py --scenario walk --split-s 0``), each kind's seed lowest in it is
picked once for every scenario, and issue 19's comparison targets are read with those seeds.

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
from stride_paper.seeds import cell_at_most, headline_picks, in_headline, kind_and_seed, seed_means

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
    seeds = _seed_cells(table)
    picks = headline_picks(table)
    val = validation_losses([r for r in table["rows"] if in_headline(r, picks)
                             and kind_and_seed(r)[0] in KINDS], models)
    cells = []
    for sc in dict.fromkeys(sc for sc, kind in seeds if kind in KINDS):
        for kind in KINDS:
            means = {s: c["vel_rmse"] for s, c in seeds.get((sc, kind), {}).items()
                     if np.isfinite(c["vel_rmse"])}  # seeds with an upright draw
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


def _seed_cells(table: dict) -> dict[tuple[str, str], dict[int, dict]]:
    """The headline's rows as ``(scenario, kind) -> {seed: {vel_rmse, falls, episodes}}`` for the
    three model kinds and the policy (one seed, 0); ``vel_rmse`` over the draws that stayed up
    (``stride_paper.seeds.seed_means``; NaN where every draw fell)."""
    picks = headline_picks(table)
    if not picks:
        raise ValueError("the table names no headline parts: nothing says which rows are the current planner")
    groups: dict[tuple[str, str, int], list[dict]] = {}
    for r in table["rows"]:
        kind, seed = kind_and_seed(r)
        if in_headline(r, picks) and kind in ("policy",) + KINDS:
            groups.setdefault((r["scenario"], kind, seed), []).append(r)
    out: dict[tuple[str, str], dict[int, dict]] = {}
    for (sc, kind, seed), rows in groups.items():
        means = seed_means(rows)
        out.setdefault((sc, kind), {})[seed] = dict(
            vel_rmse=means.get(seed, float("nan")), falls=sum(bool(r["fell"]) for r in rows),
            episodes=len(rows))
    return {k: dict(sorted(per.items())) for k, per in out.items()}


def _pooled(per_seed: dict[int, dict]) -> dict:
    """A kind's cell over all its seeds, as issue 19's targets read it: the mean of the seeds'
    means (those with an upright draw), falls and episodes summed."""
    up = [c["vel_rmse"] for c in per_seed.values() if np.isfinite(c["vel_rmse"])]
    return dict(vel_rmse=float(np.mean(up)) if up else float("nan"),
                falls=sum(c["falls"] for c in per_seed.values()),
                episodes=sum(c["episodes"] for c in per_seed.values()))


def _counts(scenarios: list[str], cell) -> dict:
    """Issue 19's two comparison targets with each kind's cell in a scenario given by
    ``cell(scenario, kind)`` (None: not run): STRIDE at most the policy (in >= 75% of the
    scenarios), at most DeLaN + MLP and ONN (every comparison); ``stride_paper.seeds.cell_at_most``."""
    pol = [cell_at_most(cell(sc, "stride"), cell(sc, "policy")) for sc in scenarios]
    base = [cell_at_most(cell(sc, "stride"), cell(sc, k)) for sc in scenarios for k in ("delan", "onn")]
    pol, base = [v for v in pol if v is not None], [v for v in base if v is not None]
    return dict(at_most_policy=sum(pol), of_policy=len(pol),
                at_most_policy_met=bool(pol) and sum(pol) >= 0.75 * len(pol),
                at_most_baselines=sum(base), of_baselines=len(base),
                at_most_baselines_met=bool(base) and all(base))


def picked_once(table: dict, errors: dict[tuple[str, int], dict], source: str) -> dict:
    """Each kind represented by one trained seed, chosen once before planning by a model error
    measured on episodes outside the table (``source``, e.g. the policy's level walk): per
    metric of :data:`METRICS` the seed lowest in it, then issue 19's comparison targets with
    those seeds in every scenario, beside the targets' own reading (the mean over seeds) and the
    per-scenario best seed (known only after planning: a bound, not a selection)."""
    seeds = _seed_cells(table)
    scenarios = list(dict.fromkeys(sc for sc, _ in seeds))
    trained = {k: sorted({s for (_, kind), per in seeds.items() if kind == k for s in per}) for k in KINDS}
    for k, ss in trained.items():
        missing = [s for s in ss if (k, s) not in errors]
        if missing:
            raise ValueError(f"{source}: the model-error report has no {k} seed(s) {missing} "
                             f"(the table's {k} seeds: {ss})")
    policy = lambda sc: _pooled(seeds[(sc, "policy")]) if (sc, "policy") in seeds else None  # noqa: E731
    rules = {}
    for m in METRICS:
        pick = {k: min(ss, key=lambda s: errors[(k, s)][m]) for k, ss in trained.items() if ss}

        def cell(sc, kind, pick=pick):
            if kind == "policy":
                return policy(sc)
            return seeds.get((sc, kind), {}).get(pick.get(kind))
        rules[m] = dict(pick=pick, **_counts(scenarios, cell),
                        stride=[dict(scenario=sc, **(cell(sc, "stride") or {})) for sc in scenarios])

    def mean(sc, kind):
        return policy(sc) if kind == "policy" else (_pooled(seeds[(sc, kind)]) if (sc, kind) in seeds else None)

    def best(sc, kind):
        if kind == "policy":
            return policy(sc)
        per = seeds.get((sc, kind))
        return min(per.values(), key=lambda c: (c["falls"] / c["episodes"],
                                                np.nan_to_num(c["vel_rmse"], nan=np.inf))) if per else None
    return dict(source=source, rules=rules, mean=_counts(scenarios, mean),
                best_in_hindsight=_counts(scenarios, best),
                per_seed={k: {str(s): {m: errors[(k, s)][m] for m in METRICS} for s in ss}
                          for k, ss in trained.items()})


def _picked_markdown(p: dict) -> list[str]:
    def count(c):
        return (f"{c['at_most_policy']} of {c['of_policy']}{' (met)' if c['at_most_policy_met'] else ''} | "
                f"{c['at_most_baselines']} of {c['of_baselines']}{' (met)' if c['at_most_baselines_met'] else ''}")
    lines = [f"Each kind represented by one trained seed, chosen once before planning by its one-period "
             f"model error on episodes outside the table (`{p['source']}`), then issue 19's comparison "
             f"targets with those seeds in every scenario (STRIDE at most the policy in >= 75% of the "
             f"scenarios; at most DeLaN + MLP's and ONN's in every comparison). The seeds' errors there "
             f"(stride / delan / onn, seeds in order): "
             + "; ".join(f"{m}: " + ", ".join(f"{k} " + " / ".join(f"{v[m]:.3f}" for v in per.values())
                                              for k, per in p["per_seed"].items()) for m in METRICS) + ".", "",
             "| seeds | picks (stride, delan, onn) | STRIDE <= policy | <= DeLaN and ONN | STRIDE per scenario |",
             "|---|---|---|---|---|",
             f"| mean over seeds (the targets) | all | {count(p['mean'])} | |"]
    for m, r in p["rules"].items():
        per = ", ".join(f"{c['scenario']} {c['vel_rmse']:.4f}" for c in r["stride"] if "vel_rmse" in c)
        picks = ", ".join(f"s{r['pick'][k]}" for k in KINDS if k in r["pick"])
        lines.append(f"| lowest {m} | {picks} | {count(r)} | {per} |")
    lines += [f"| best per scenario (known only after planning) | - | {count(p['best_in_hindsight'])} | |", ""]
    return lines


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
        for p in res.get("picked_once", []):
            lines += _picked_markdown(p)
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("tables", nargs="+", help="ROBOT=MERGED.json:MODELS_DIR")
    ap.add_argument("--model-error", action="append", default=[], metavar="ROBOT:SCENARIO=JSON",
                    help="a scenario_model_error.py report of the same models, compared per kind "
                         "with the seeds' planning error (repeatable)")
    ap.add_argument("--pick-by", action="append", default=[], metavar="ROBOT=JSON",
                    help="a scenario_model_error.py report of the same models on episodes outside "
                         "the table (e.g. the policy's level walk): each kind's seed picked once "
                         "by each metric there, and the targets' comparisons with those seeds")
    ap.add_argument("--out", required=True, help="writes OUT.md and OUT.json")
    a = ap.parse_args(argv)
    results, tables = {}, {}
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
        tables[robot] = path
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
    for spec in a.pick_by:
        robot, eq, path = spec.partition("=")
        if not eq or robot not in results:
            ap.error(f"--pick-by {spec!r}: expected ROBOT=JSON, ROBOT one of {sorted(results)}")
        if not pathlib.Path(path).is_file():
            ap.error(f"--pick-by {spec!r}: {path}: no such report")
        table = json.loads(pathlib.Path(tables[robot]).read_text())
        results[robot].setdefault("picked_once", []).append(
            picked_once(table, model_errors(json.loads(pathlib.Path(path).read_text())), path))
    command = "python experiments/seed_selection.py " + " ".join(sys.argv[1:] if argv is None else argv)
    stem = io.write_table(a.out, dict(command=command, robots=results), markdown(results, command))
    print(f"wrote {stem}.{{md,json}}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
