"""Does a model's validation loss pick the trained seed that plans best? Per robot, scenario and
model kind of a merged closed-loop table's headline: each trained seed's mean velocity RMSE
(``stride_paper.seeds.seed_means``: its planner draws that stayed up) beside the seed the
training's own held-out loss would choose (``best_val`` of the run's ``summary.json``), the mean
over seeds (what issue 19's targets read) and the best seed (known only after planning).

    python experiments/seed_selection.py \\
        go1=results/closed_loop_go1_gpu/closed_loop.json:results/models/go1_walk_ppo_go1_slope_slope20_tw1_tf0.25_com \\
        g1=results/closed_loop_g1_gpu/closed_loop.json:results/models/g1_walk_ppo_g1_slope_slope15_tw1_tf0.25 \\
        --out results/closed_loop_seed_selection

``ROBOT=TABLE:MODELS``: a row's run folder (its ``run`` field, e.g. ``fm/slope/stride-s1``, a
copy carried to the GPU) is looked up by its name in ``MODELS``. The losses of different kinds
are in different units (STRIDE's includes its flow-matching term): seeds are compared within a
kind only. Writes ``OUT.md`` and ``OUT.json``; the targets keep the mean over seeds.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

import numpy as np

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
    cells, hits = [], {k: [0, 0] for k in KINDS}
    for sc in dict.fromkeys(r["scenario"] for r in rows):
        for kind in KINDS:
            means = seed_means([r for r in rows if r["scenario"] == sc and kind_and_seed(r)[0] == kind])
            if len(means) < 2:
                continue
            pick = min(means, key=lambda s: val[(kind, s)])
            best = min(means, key=means.get)
            hits[kind][0] += pick == best
            hits[kind][1] += 1
            cells.append(dict(scenario=sc, kind=kind, seeds={str(s): v for s, v in means.items()},
                              val={str(s): val[(kind, s)] for s in means}, pick=pick, best=best,
                              picked=means[pick], mean=float(np.mean(list(means.values()))),
                              best_value=means[best]))
    return dict(cells=cells, hits={k: dict(best_picked=h[0], of=h[1]) for k, h in hits.items()})


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
        picked = "; ".join(f"{k}: " + ", ".join(f"s{s} in {n}" for s, n in sorted(
            {s: sum(c["pick"] == s for c in res["cells"] if c["kind"] == k)
             for s in {c["pick"] for c in res["cells"] if c["kind"] == k}}.items()))
            for k in res["hits"])
        lines += ["", f"- the validation pick is the best-planning seed: {hit}",
                  f"- the picks (one per kind, the same seed in every scenario where the same seeds "
                  f"ran): {picked}; cells of one pick are not independent draws", ""]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("tables", nargs="+", help="ROBOT=MERGED.json:MODELS_DIR")
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
    command = "python experiments/seed_selection.py " + " ".join(sys.argv[1:] if argv is None else argv)
    stem = io.write_table(a.out, dict(command=command, robots=results), markdown(results, command))
    print(f"wrote {stem}.{{md,json}}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
