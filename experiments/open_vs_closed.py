"""Which open-loop number ranks planners? Across independently trained models (every trained seed
of every model kind), the rank correlation between each open-loop metric of Table I and the
closed-loop velocity RMSE of planning through the same model, per scenario.

    python experiments/open_vs_closed.py \\
        --pair "G1=results/table1/g1_walk_tw1_tf0.25/table.json:results/closed_loop_g1_gpu/trained_seeds.json" \\
        --pair "Go1=results/table1/go1_walk_tw1_tf0.25/table.json:results/closed_loop_go1_gpu/trained_seeds.json" \\
        --out results/planning_diagnosis/open_vs_closed

A pair joins a Table I (``table.json``: one run per model and seed; several joined by ``+``, a
later table's run replacing an earlier one's of the same model and seed: seeds retrained apart)
with the closed-loop rows of the same runs (``experiments/trained_seeds.py``'s JSON). Writes ``OUT.md`` / ``OUT.json`` (Spearman's
rho and a permutation p-value per robot, scenario and metric; the joined points) and ``OUT.png``
(closed-loop RMSE against two of the metrics, one dot per trained model). With 8-9 models per
scenario a rank correlation is a coarse measure: the p-values say how coarse.
"""

from __future__ import annotations

import argparse
import json
import pathlib

import numpy as np
from scipy import stats

from stride_jax.io import write_table

METRICS = {  # name -> (label, getter on a Table I run row)
    "per_sample": ("state RMSE per sample", lambda r: r["state"]["mean"]),
    "sample_mean": ("state RMSE of the samples' mean", lambda r: r["distribution"]["mean_of_samples"]),
    "energy": ("energy score", lambda r: r["distribution"]["energy"]),
    "crps": ("CRPS", lambda r: r["distribution"]["crps"]),
}
PLOTTED = ("per_sample", "energy")


def spearman(x, y, permutations: int = 20000, seed: int = 0) -> tuple[float, float]:
    """Spearman's rho of ``x`` and ``y`` (ties share their mean rank) and its two-sided
    permutation p-value, every permutation at once."""
    rx, ry = stats.rankdata(x), stats.rankdata(y)
    rx, ry = rx - rx.mean(), ry - ry.mean()
    norm = np.sqrt((rx @ rx) * (ry @ ry))
    rho = float(rx @ ry / norm)
    perm = np.random.default_rng(seed).permuted(np.tile(ry, (permutations, 1)), axis=1)
    null = perm @ rx / norm
    return rho, float((1 + (np.abs(null) >= abs(rho) - 1e-12).sum()) / (1 + permutations))


def join(table: dict, seeds: dict) -> list[dict]:
    """One point per (scenario, model kind, trained seed) present in both: the run's open-loop
    metrics and its planner's velocity RMSE (rows that fell are left out)."""
    runs = {(r["model"], int(r["seed"])): r for r in table["runs"]}
    points = []
    for g in seeds["groups"]:
        for seed, v, fell in zip(g["seeds"], g["vel_rmse"], g["fell"], strict=True):
            run = runs.get((g["model"], int(seed)))
            if run is None or fell:
                continue
            m = {}
            for k, (_, get) in METRICS.items():
                try:
                    m[k] = float(get(run))
                except (KeyError, TypeError):
                    pass
            points.append({"scenario": g["scenario"], "model": g["model"], "seed": int(seed),
                           "vel_rmse": float(v), **m})
    return points


def merge_tables(tables: list[dict]) -> dict:
    """Table I runs of several tables as one: a later table's run of the same model and seed
    replaces an earlier one's."""
    runs = {}
    for t in tables:
        runs.update({(r["model"], int(r["seed"])): r for r in t["runs"]})
    return {"runs": list(runs.values())}


def correlations(points: list[dict], permutations: int) -> list[dict]:
    out = []
    for sc in dict.fromkeys(p["scenario"] for p in points):
        pts = [p for p in points if p["scenario"] == sc]
        for k, (label, _) in METRICS.items():
            use = [p for p in pts if k in p]
            if len(use) < 4:
                continue
            rho, pv = spearman([p[k] for p in use], [p["vel_rmse"] for p in use], permutations)
            out.append({"scenario": sc, "metric": k, "label": label, "n": len(use), "rho": rho, "p": pv})
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pair", action="append", required=True, help="ROBOT=TABLE_JSON:TRAINED_SEEDS_JSON")
    ap.add_argument("--out", required=True, help="path stem: writes STEM.md, .json, .png")
    ap.add_argument("--permutations", type=int, default=20000)
    a = ap.parse_args(argv)
    result = {"command": "python experiments/open_vs_closed.py " + " ".join(
        f'--pair "{p}"' for p in a.pair) + f" --out {a.out}", "robots": {}}
    for spec in a.pair:
        robot, _, paths = spec.partition("=")
        table_path, _, seeds_path = paths.partition(":")
        if not (robot and table_path and seeds_path):
            raise SystemExit(f"--pair {spec!r}: expected ROBOT=TABLE_JSON:TRAINED_SEEDS_JSON")
        tables = table_path.split("+")
        for p in (*tables, seeds_path):
            if not pathlib.Path(p).is_file():
                raise SystemExit(f"--pair {spec!r}: {p} does not exist")
        points = join(merge_tables([json.loads(pathlib.Path(t).read_text()) for t in tables]),
                      json.loads(pathlib.Path(seeds_path).read_text()))
        if not points:
            raise SystemExit(f"--pair {spec!r}: no run of the table has closed-loop rows")
        result["robots"][robot] = {"table": table_path, "trained_seeds": seeds_path, "points": points,
                                   "correlations": correlations(points, a.permutations)}
    lines = ["# Which open-loop number ranks planners?", "", f"Command: `{result['command']}`", "",
             "Spearman's rho between each open-loop metric of Table I and the closed-loop velocity RMSE "
             "of planning through the same trained model, over every trained seed of STRIDE, DeLaN + MLP "
             "and ONN (ONN has no samples: its energy score and CRPS are those of a point forecast). "
             "Positive: the better the open-loop number, the better the planner. p: two-sided permutation "
             f"test ({a.permutations} permutations); n: models.", "",
             "| robot | scenario | n | " + " | ".join(label for label, _ in METRICS.values()) + " |",
             "|---|---|---:|" + "---:|" * len(METRICS)]
    for robot, r in result["robots"].items():
        for sc in dict.fromkeys(c["scenario"] for c in r["correlations"]):
            cs = {c["metric"]: c for c in r["correlations"] if c["scenario"] == sc}
            n = max(c["n"] for c in cs.values())
            cells = [f"{cs[k]['rho']:+.2f} (p {cs[k]['p']:.2f})" if k in cs else "-" for k in METRICS]
            lines.append(f"| {robot} | {sc} | {n} | " + " | ".join(cells) + " |")
    out = pathlib.Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_table(out, result, "\n".join(lines) + "\n")
    _plot(result, out.with_suffix(".png"))
    print(f"wrote {out}.{{md,json,png}}")


def _plot(result: dict, path: pathlib.Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [(robot, sc) for robot, r in result["robots"].items()  # scenarios with a correlation
              for sc in dict.fromkeys(c["scenario"] for c in r["correlations"])]
    fig, axes = plt.subplots(len(PLOTTED), len(panels), figsize=(3.2 * len(panels), 2.8 * len(PLOTTED)),
                             squeeze=False)
    colors = {"stride": "C0", "delan": "C1", "onn": "C2"}
    for j, (robot, sc) in enumerate(panels):
        r = result["robots"][robot]
        pts = [p for p in r["points"] if p["scenario"] == sc]
        for i, k in enumerate(PLOTTED):
            ax = axes[i, j]
            for p in pts:
                if k in p:
                    ax.scatter(p[k], p["vel_rmse"], color=colors.get(p["model"], "k"), s=20,
                               label=p["model"])
            c = next((c for c in r["correlations"] if c["scenario"] == sc and c["metric"] == k), None)
            ax.set_title(f"{robot} {sc}" + (f": rho {c['rho']:+.2f}" if c else ""), fontsize=9)
            ax.set_xlabel(METRICS[k][0], fontsize=8)
            if j == 0:
                ax.set_ylabel("closed-loop vel RMSE (m/s)", fontsize=8)
            ax.tick_params(labelsize=7)
    seen = {}  # every kind in any panel (the first may lack one: rough ground ran two kinds)
    for ax in axes.flat:
        for h, label in zip(*ax.get_legend_handles_labels()):
            seen.setdefault(label, h)
    fig.legend(seen.values(), seen.keys(), loc="upper right", fontsize=8)
    fig.tight_layout(rect=(0, 0, 0.93, 1))
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()
