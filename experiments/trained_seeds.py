"""Closed loop over trained seeds: planners through several independently trained copies of each
model (rows named MODEL, MODEL_s1, MODEL_s2, ...; the seed is read from the row's run folder,
``.../MODEL-sN``, or from the name) gathered per (scenario, model kind), beside reference rows of
other controllers: a table (``OUT.md``, ``OUT.json``) and a figure (``OUT.png``, one dot per
episode, a cross where it fell, the references as horizontal ticks).

    python experiments/trained_seeds.py PART/closed_loop.json [...] --out results/x/trained_seeds \\
        --reference results/closed_loop_g1_gpu/closed_loop.json \\
        --ref "policy=policy@walk_push,rough2_gov" --ref "oracle (MJX)=oracle@oracle_push"

One trained model is one draw of its training (data order, initialisation): a closed-loop
comparison of learned models needs the spread over trained seeds, which this table gives; and
one episode is one draw of the planner (a fall can hinge on float rounding): parts run with
``--episodes N`` give each trained seed N planner draws, and the table their fall counts.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import textwrap

import numpy as np

from stride_jax import io
from stride_jax.jobs import closed_loop
from stride_paper.seeds import kind_and_seed, seed_means, welch


def gather(rows: list[dict]) -> list[dict]:
    """Per (scenario, model kind), in first-seen order: each trained seed's episodes (planner
    draws: the row's ``seed``, as ``--episodes N`` writes them), its mean velocity RMSE over the
    draws that stayed up (over all where none did) and falls; the mean and worst RMSE over all
    the episodes that stayed up (NaN: none did). Two rows of the same scenario, kind, trained
    seed and planner seed are an error (two parts ran the same model: pick one)."""
    groups: dict[tuple[str, str], dict[int, dict[int, dict]]] = {}
    for r in rows:
        kind, seed = kind_and_seed(r)
        draw = int(r.get("seed") or 0)
        got = groups.setdefault((r["scenario"], kind), {}).setdefault(seed, {})
        if draw in got:
            at = f" at planner seed {draw}" if draw else ""
            raise ValueError(f"scenario {r['scenario']!r}: two rows of {kind} seed {seed}{at} "
                             f"({got[draw]['model']} and {r['model']})")
        got[draw] = r
    out = []
    for (sc, kind), got in groups.items():
        seeds = sorted(got)
        episodes = [dict(seed=s, draw=d, vel_rmse=float(got[s][d]["vel_rmse"]),
                         fell=bool(got[s][d]["fell"])) for s in seeds for d in sorted(got[s])]
        per = {s: [e for e in episodes if e["seed"] == s] for s in seeds}
        up = [e["vel_rmse"] for e in episodes if not e["fell"]]

        means = seed_means([r for s in seeds for r in got[s].values()], fallen="all")
        out.append(dict(scenario=sc, model=kind, seeds=seeds,
                        vel_rmse=[means.get(s, float("nan")) for s in seeds],
                        fell=[all(e["fell"] for e in per[s]) for s in seeds],
                        draws=[len(per[s]) for s in seeds],
                        falls=[sum(e["fell"] for e in per[s]) for s in seeds],
                        episodes=episodes,
                        ms_per_step=float(np.mean([got[s][d]["ms_per_step"]
                                                   for s in seeds for d in got[s]])),
                        side_by_side=max(int(got[s][d].get("side_by_side") or 1)
                                         for s in seeds for d in got[s]),
                        vel_rmse_mean=float(np.mean(up)) if up else float("nan"),
                        vel_rmse_worst=float(max(up)) if up else float("nan")))
    return out


def versus(groups: list[dict], against: str = "stride", level: float = 0.9) -> list[dict]:
    """Adds to each group of another kind ``vs``: its mean RMSE minus ``against``'s in the same
    scenario over the trained seeds that stayed up (each seed one draw of its training: the
    mean over its planner draws), with Welch's ``level`` t-interval (None: fewer than two such
    seeds on either side, no spread on either, or no ``against`` group). An interval that holds
    0 says the kinds are not told apart by these seeds."""
    base = {g["scenario"]: g for g in groups if g["model"] == against}
    for g in groups:
        b = base.get(g["scenario"])
        g["vs"] = None
        if b is None or b is g:
            continue
        x = [v for v, f in zip(g["vel_rmse"], g["fell"]) if not f]
        y = [v for v, f in zip(b["vel_rmse"], b["fell"]) if not f]
        w = welch(x, y, level)
        if w is not None:
            g["vs"] = dict(against=against, level=level, diff=w["diff"], lo=w["lo"], hi=w["hi"],
                           seeds=w["n"])
    return groups


def table(groups: list[dict], refs: dict[str, dict[str, dict]]) -> list[str]:
    """Markdown lines: one row per (scenario, kind), its difference to the ``versus`` kind
    where measured, the references of the scenario beside."""
    vs = next((g["vs"] for g in groups if g.get("vs")), None)
    vs_head = [f"minus {vs['against']} ({vs['level']:.0%} interval)"] if vs else []
    head = ["scenario", "model", "trained seeds", "vel RMSE per seed (m/s)", "mean", "worst",
            "falls", "ms/step"] + vs_head + list(refs)
    lines = ["| " + " | ".join(head) + " |", "|---|---|---|---|" + "---:|" * (len(head) - 4)]
    for g in groups:
        per = " / ".join(f"{v:.3f}" + (f" ({k}/{n} fell)" if n > 1 and k else
                                         " (fell)" if k else "")
                         for v, k, n in zip(g["vel_rmse"], g["falls"], g["draws"]))
        ref = [refs[k].get(g["scenario"]) for k in refs]
        ref = [("falls" if r["fell"] else f"{r['vel_rmse']:.3f}") if r else "" for r in ref]
        d = g.get("vs")
        cell = ([f"{d['diff']:+.3f} [{d['lo']:+.3f}, {d['hi']:+.3f}]" if d else ""]
                if vs else [])
        row = [g["scenario"], g["model"], ", ".join(map(str, g["seeds"])), per,
               f"{g['vel_rmse_mean']:.3f}", f"{g['vel_rmse_worst']:.3f}",
               f"{sum(g['falls'])}/{sum(g['draws'])}", _ms(g)] + cell + ref
        lines.append("| " + " | ".join(row) + " |")
    return lines


def _ms(g: dict) -> str:
    """The ms/step cell: one control step's wall time, of all the episodes that ran side by side
    in one vmapped program where there were several (``--episodes N``), said so."""
    n = g.get("side_by_side", 1)
    return f"{g['ms_per_step']:.1f}" + (f" ({n} together)" if n > 1 else "")


def figure(groups: list[dict], refs: dict[str, dict[str, dict]], out: pathlib.Path,
           title: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenarios = list(dict.fromkeys(g["scenario"] for g in groups))
    kinds = list(dict.fromkeys(g["model"] for g in groups))
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    fig, ax = plt.subplots(figsize=(max(6.0, 2.2 * len(scenarios) + 2), 4.0))
    width = 0.8 / max(len(kinds), 1)
    for i, kind in enumerate(kinds):  # the legend names each kind once, as a dot
        ax.plot([], [], "o", color=colors[i % len(colors)], ms=6, label=kind)
    ax.plot([], [], "x", color="grey", ms=6, label="fell")
    for g in groups:
        j, i = scenarios.index(g["scenario"]), kinds.index(g["model"])
        x = j - 0.4 + (i + 0.5) * width
        for e in g["episodes"]:
            ax.plot(x, e["vel_rmse"], "x" if e["fell"] else "o", color=colors[i % len(colors)],
                    ms=6)
        if np.isfinite(g["vel_rmse_mean"]):
            ax.hlines(g["vel_rmse_mean"], x - 0.3 * width, x + 0.3 * width,
                      color=colors[i % len(colors)], lw=2)
    styles = ["--", ":", "-.", (0, (5, 1))]
    for n, (label, got) in enumerate(refs.items()):
        for j, sc in enumerate(scenarios):
            r = got.get(sc)
            if r is not None and not r["fell"]:
                ax.hlines(r["vel_rmse"], j - 0.45, j + 0.45, color="k", ls=styles[n % 4], lw=1,
                          label=label if sc == next((s for s in scenarios if s in got), None)
                          else None)
    ax.set_xticks(range(len(scenarios)))
    ax.set_xticklabels(scenarios)
    ax.set_ylabel("velocity RMSE while upright (m/s)")
    ax.set_ylim(bottom=0)
    ax.set_title("\n".join(textwrap.wrap(title, 90)), fontsize=9)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    io.atomic_write(out, lambda f: fig.savefig(f, format="png", dpi=130))
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("tables", nargs="+",
                    help="closed_loop.json files (or their folders); VARIANT=PATH names the "
                         "planner its rows ran (their kinds read 'stride (VARIANT)', ...)")
    ap.add_argument("--out", required=True, help="path stem: writes STEM.md, .json, .png")
    ap.add_argument("--reference", default="", help="a merged closed_loop.json for --ref")
    ap.add_argument("--ref", action="append", default=[],
                    help="LABEL=MODEL[@PART,PART...]: a reference controller's rows")
    ap.add_argument("--versus", default="stride",
                    help="the kind every other is compared with (mean difference, Welch interval)")
    ap.add_argument("--title", default="")
    a = ap.parse_args(argv)
    rows, sources = [], []
    for t in a.tables:
        variant, _, where = t.rpartition("=")
        if variant and pathlib.Path(t).exists():  # a path with "=" in it, no variant
            variant, where = "", t
        path = pathlib.Path(where)
        path = path / "closed_loop.json" if path.is_dir() else path
        if not path.is_file():
            raise SystemExit(f"{path}: no closed-loop table")
        rows += [dict(r, variant=variant) if variant else r
                 for r in json.loads(path.read_text())["rows"]]
        sources.append(f"{variant}={path}" if variant else str(path))
    refs: dict[str, dict[str, dict]] = {}
    if a.ref and not a.reference:
        raise SystemExit("--ref needs --reference (the table the reference rows come from)")
    if a.reference and not pathlib.Path(a.reference).is_file():
        raise SystemExit(f"--reference {a.reference}: no such closed-loop table")
    ref_rows = json.loads(pathlib.Path(a.reference).read_text())["rows"] if a.reference else []
    for spec in a.ref:
        try:
            label, model, parts = closed_loop.parse_pick(spec, "--ref")
        except ValueError as e:
            raise SystemExit(str(e)) from None
        refs[label] = closed_loop.select(ref_rows, model, parts)
        if not refs[label]:
            raise SystemExit(f"--ref {spec!r}: no row of {model!r} in {a.reference}")
    groups = versus(gather(rows), a.versus)
    stem = pathlib.Path(a.out)
    stem.parent.mkdir(parents=True, exist_ok=True)
    md = [f"# {a.title or 'Closed loop over trained seeds'}", "",
          "Sources: " + ", ".join(f"`{s}`" for s in sources)
          + (f"; references from `{a.reference}` ({', '.join(a.ref)})" if a.ref else ""), "",
          "Per seed: the mean over its planner draws that stayed up (k/n fell: of its n draws); "
          "mean and worst: over every episode that stayed up; falls: of all episodes; ms/step: "
          "one control step's wall time (N together: of N episodes in one vmapped program). "
          f"Minus {a.versus}: the difference of the means over the trained seeds that stayed up, "
          "with Welch's 90% t-interval (one value per trained seed; an interval holding 0 does "
          "not tell the kinds apart).", ""]
    io.write_table(stem, dict(title=a.title, sources=sources, reference=a.reference, refs=a.ref,
                              groups=groups), "\n".join(md + table(groups, refs)) + "\n")
    figure(groups, refs, stem.with_suffix(".png"), a.title)
    print(f"wrote {stem}.{{md,json,png}} ({len(groups)} groups)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
