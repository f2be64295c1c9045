"""Closed-loop planners side by side, per scenario: each variant's velocity RMSE as the
headline's targets count it (the mean over trained seeds of each seed's mean over its draws),
its falls, its controller's own time per period (``controller_ms``, where timed) and the periods
its plans arrive late (``latency_steps``).

    python experiments/closed_loop_variants.py "LABEL=PATH[:PART]" ... --out FILE.md \\
        [--scenarios A,B] [--models NAME,...] [--paired-against LABEL]

A LABEL given more than once pools the rows of its files (one variant run in several parts).
PATH: a ``closed_loop.json`` (a run's, or a merged table whose rows name their ``part``; PART
keeps that part's rows). Rows are grouped by scenario and by trained seed
(``stride_paper.seeds.seed_means``: the run folder's ``-sN``, else the name's ``_sN``).
``--models`` keeps the rows of those model names alone (``stride``: trained seed 0 of a run over
three; a merged table's ``stride@PART`` is ``stride``). ``--paired-against LABEL`` adds each
variant's difference from that one, episode by episode (the same scenario, model name, planner
seed and episode: the same ground and draws where the runs shared their flags), with its 90%
t-interval over every pair both kept up: pooled over scenarios of different scales, a summary
(the per-scenario means stand beside it), and over draws and trained seeds as if independent."""

from __future__ import annotations

import argparse
import json
import pathlib
import shlex
import sys

import numpy as np

from stride_jax.io import atomic_write_text
from stride_jax.jobs.select_learned import paired
from stride_paper.seeds import seed_means


def rows_of(spec: str) -> tuple[str, list[dict]]:
    label, _, where = spec.partition("=")
    if not where:
        raise ValueError(f"{spec!r}: give LABEL=PATH[:PART]")
    path, _, part = where.partition(":")
    if not pathlib.Path(path).is_file():
        raise FileNotFoundError(f"{path}: no closed_loop.json")
    rows = json.loads(pathlib.Path(path).read_text())["rows"]
    if part:
        rows = [r for r in rows if r.get("part") == part]
        if not rows:
            raise ValueError(f"{path}: no rows of part {part!r}")
    return label, rows


def summary(rows: list[dict]) -> dict[str, dict]:
    """Per scenario: the mean over trained seeds of their mean RMSE over draws that stayed up,
    each seed's mean, falls over episodes, the median controller ms and the latency."""
    out = {}
    for sc in dict.fromkeys(r["scenario"] for r in rows):
        mine = [r for r in rows if r["scenario"] == sc]
        per_seed = list(seed_means(mine).values())
        ctl = [r["controller_ms"] for r in mine if r.get("controller_ms") is not None]
        out[sc] = dict(rmse=float(np.mean(per_seed)) if per_seed else float("nan"),
                       per_seed=per_seed, falls=sum(bool(r["fell"]) for r in mine),
                       episodes=len(mine), controller_ms=float(np.median(ctl)) if ctl else None,
                       latency_steps=mine[0].get("latency_steps") or 0)
    return out


def _name(r: dict) -> str:
    """A row's model name (a merged table's ``NAME@PART`` is ``NAME``)."""
    return r["model"].partition("@")[0]


def _key(r: dict) -> tuple:
    return r["scenario"], _name(r), r.get("seed"), r.get("episode")


def paired_rows(rows: list[dict], ref: list[dict]) -> dict:
    """``rows`` against ``ref`` episode by episode (:func:`_key`), both up: the pairs, the mean
    difference with its 90% t-interval (``select_learned.paired``; None under two pairs or no
    spread) and per scenario the mean difference."""
    theirs = {_key(r): r for r in ref if not r["fell"]}
    mine = [r for r in rows if not r["fell"] and _key(r) in theirs]
    x = np.array([r["vel_rmse"] for r in mine])
    y = np.array([theirs[_key(r)]["vel_rmse"] for r in mine])
    d, ci = x - y, paired(x, y) or {}
    per_sc = {sc: float(np.mean([v for r, v in zip(mine, d) if r["scenario"] == sc]))
              for sc in dict.fromkeys(r["scenario"] for r in mine)}
    return dict(n=len(d), diff=float(d.mean()) if len(d) else float("nan"), lo=ci.get("lo"),
                hi=ci.get("hi"), per_scenario=per_sc)


def paired_table(pooled: dict[str, list[dict]], ref_label: str) -> list[str]:
    if ref_label not in pooled:
        raise ValueError(f"--paired-against {ref_label!r}: no such variant "
                         f"({', '.join(pooled)})")
    ref = pooled[ref_label]
    lines = [f"Minus `{ref_label}`, episode by episode (m/s; both up; 90% t-interval over the "
             "pairs), and per scenario the mean difference:", "",
             "| variant | pairs | minus the reference [90%] | scenarios below it | per scenario |",
             "|---|---:|---|---:|---|"]
    for label, rows in pooled.items():
        if label == ref_label:
            continue
        p = paired_rows(rows, ref)
        if not p["n"]:  # another model's rows (the policy beside the planners), other draws
            lines.append(f"| {label} | 0 | no episode pairs with one of {ref_label!r} (scenario, "
                         "model, seed, episode) | - | - |")
            continue
        ci = "" if p["lo"] is None else f" [{p['lo']:+.4f}, {p['hi']:+.4f}]"
        below = sum(v < 0 for v in p["per_scenario"].values())
        lines.append(f"| {label} | {p['n']} | {p['diff']:+.4f}{ci} | {below} of "
                     f"{len(p['per_scenario'])} | "
                     + ", ".join(f"{sc} {v:+.4f}" for sc, v in p["per_scenario"].items()) + " |")
    return lines


def table(variants: list[tuple[str, dict]]) -> list[str]:
    scenarios = list(dict.fromkeys(sc for _, s in variants for sc in s))
    lines = ["| variant | controller ms | periods late | "
             + " | ".join(f"{sc}: vel RMSE (seeds) | {sc}: falls" for sc in scenarios) + " |",
             "|---|---:|---:|" + "---|---:|" * len(scenarios)]
    for label, s in variants:
        ctl = [v["controller_ms"] for v in s.values() if v["controller_ms"] is not None]
        cells = []
        for sc in scenarios:
            v = s.get(sc)
            cells += (["-", "-"] if v is None else
                      [f"{v['rmse']:.4f} ({' / '.join(f'{x:.4f}' for x in v['per_seed'])})",
                       f"{v['falls']}/{v['episodes']}"])
        lat = max(v["latency_steps"] for v in s.values())
        lines.append(f"| {label} | {np.median(ctl):.1f} | {lat} | " if ctl else
                     f"| {label} | - | {lat} | ")
        lines[-1] += " | ".join(cells) + " |"
    return lines


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("variants", nargs="+", help="LABEL=PATH[:PART]")
    ap.add_argument("--out", required=True, help="the markdown table to write")
    ap.add_argument("--scenarios", default="", help="comma-separated: only these (all: '')")
    ap.add_argument("--models", default="", help="comma-separated model names: only these rows")
    ap.add_argument("--paired-against", default="", metavar="LABEL",
                    help="each variant's episode-by-episode difference from this one")
    a = ap.parse_args(argv)
    keep = set(filter(None, a.scenarios.split(",")))
    names = set(filter(None, a.models.split(",")))
    pooled: dict[str, list[dict]] = {}  # a label given again pools its files' rows
    for label, rows in map(rows_of, a.variants):
        pooled.setdefault(label, []).extend(
            r for r in rows if (not keep or r["scenario"] in keep)
            and (not names or _name(r) in names))
    for label, rows in pooled.items():
        if not rows:
            raise ValueError(f"{label}: no rows left of the scenarios and models asked for")
    variants = [(label, summary(rows)) for label, rows in pooled.items()]
    lines = [f"Command: `python {' '.join(shlex.quote(x) for x in sys.argv)}`", "",
             "Velocity RMSE (m/s): the mean over trained seeds of each seed's mean over its "
             "draws that stayed up (each seed's in brackets); falls over all episodes; controller "
             "ms: the median of the rows' `controller_ms` (the controller's own computation per "
             "period, no world); periods late: `latency_steps`.", ""] + table(variants)
    if a.paired_against:
        lines += [""] + paired_table(pooled, a.paired_against)
    atomic_write_text(pathlib.Path(a.out), "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
