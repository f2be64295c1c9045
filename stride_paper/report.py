"""``results/REPORT.md``: each claim of the paper, its number, ours and a computed verdict.

Built only from result files on disk (paths relative to the results folder):

* ``table1/go1/table.json``, ``table1/g1/table.json`` (required): Table I, every run per seed
  (``experiments/table1.py``), and every other ``table1/<data set>/table.json``;
* ``reproduce/<preset>/summary.json``: the figures' numbers (``experiments/reproduce.py``); the
  ``paper`` preset is preferred (``reproduce/paper/`` or ``reproduce/summary.json`` tagged
  ``paper``), else ``tiny``, whose numbers test the pipeline and say nothing about the paper;
* ``mppi_latency/bench_mppi_cpu.json``, ``mppi_latency/bench_mppi_gpu.json`` (and
  ``mppi_latency/*/**/bench_mppi_*.json``): MPPI latency
  (``stride bench-mppi``) against the issue-4 targets;
* ``closed_loop*/**/*.json``: closed-loop MPPI runs (``stride_jax.jobs.closed_loop``; the
  committed ones in ``closed_loop/``);
* ``gap_bench.json``: a pointer to the gap tool's benchmark.

The paper's numbers are the constants below, each with where it is in ``stride.tex``. Every
verdict is computed from the numbers: ``holds`` / ``does not hold`` when measured, ``not run``
when the input is absent, ``not measurable`` when the runs exist but give no finite number (e.g.
every rollout diverged). Spread is the std over seeds (population std, as ``jobs/eval.py``).
"""

from __future__ import annotations

import os
import pathlib
import re

from stride_paper.report_common import (
    FAILS, FIGURES_DIR, HOLDS, NAMES, NOT_MEASURABLE, NOT_RUN, PAPER_ALLOCATION, ROBOT_NAMES,
    ROBOTS, WHERE_ALLOCATION, WHERE_NFE, WHERE_PHASE, Row, _any, _dig, _git_note, _load_json, _pm,
    _stats, _table, verdict,
)
from stride_paper.report_common import PAPER_TABLE1  # noqa: F401  (re-exported)
from stride_paper.report_control import closed_loop_rows, gap_lines, mppi_rows
from stride_paper.report_table1 import (_growth, _ratio_text, further_section, further_tables,
                                           load_table1, seed_ratio, table1_rows)
from stride_jax.io import atomic_write_text

# ------------------------------------------------------------------------ reproduce summary

def find_summary(results: pathlib.Path) -> tuple[pathlib.Path | None, str | None]:
    """The paper preset's summary.json if present, else the tiny preset's, else (None, None)."""
    rep = results / FIGURES_DIR
    found = []
    for p in [rep / "paper" / "summary.json", rep / "summary.json",
              *sorted(rep.glob("*/summary.json"))]:
        if p.is_file() and p not in [f for f, _ in found]:
            tag = _load_json(p).get("tag") or p.parent.name
            found.append((p, tag))
    for want in ("paper", "tiny"):
        for p, tag in found:
            if tag == want:
                return p, tag
    return found[0] if found else (None, None)


def summary_claims(summary: dict) -> tuple[list[dict], str]:
    """The summary's claims with verdicts recomputed from its numbers (the same criteria as
    ``claims.claims``); a note says when a stored verdict differs or recomputing failed."""
    stored = {c.get("id"): c.get("holds") for c in summary.get("claims") or []}
    try:
        from stride_paper import claims as claims_lib
        claims = claims_lib.claims(summary)
        note = "verdicts recomputed from the summary's numbers"
    except (KeyError, TypeError, ValueError, IndexError, AttributeError, ZeroDivisionError) as e:
        claims = [dict(c) for c in summary.get("claims") or []]
        note = f"recomputing failed ({type(e).__name__}: {e}); the stored verdicts are shown"
    stale = [c["id"] for c in claims if c["id"] in stored and stored[c["id"]] != c["holds"]]
    if stale:
        note += f"; stored verdicts differ for {', '.join(stale)} (summary.json is stale)"
    return claims, note


def claim_spread(summary: dict, cid: str) -> str | None:
    """Spread over seeds behind a summary claim, where the summary keeps per-seed numbers."""
    try:
        m = re.fullmatch(r"(?:state_(\w+?)_vs_(\w+)|abstract_20pct_state_(\w+))", cid)
        if m:
            robot = m.group(1) or m.group(3)
            runs = summary["horizon"]["per_run"][robot]
            other = m.group(2)
            if other is None:  # the best baseline by mean, as claims.claims
                t = summary["horizon"]["table"][robot]
                cands = {k: v["cumulative_mean"] for k, v in t.items()
                         if k != "stride" and v.get("cumulative_mean")}
                other = min(cands, key=cands.get)
            cum = lambda k: {r["seed"]: r["cumulative"] for r in runs[k]}
            r = seed_ratio(cum("stride"), cum(other))
            return "per seed " + _ratio_text(r, None, other)
        m = re.fullmatch(r"(?:force_(\w+?)_vs_(\w+)|abstract_20pct_force_(\w+))", cid)
        if m:
            robot, other = m.group(1) or m.group(3), m.group(2) or "delan"
            ps = summary["forces"]["robots"][robot]["per_seed"]
            err = lambda k: {r["seed"]: _dig(r, "overall", "error") for r in ps[k]}
            return "per seed " + _ratio_text(seed_ratio(err("stride"), err(other)), None, other)
        m = re.fullmatch(r"force_relative_(\w+)", cid)
        if m:
            ps = summary["forces"]["robots"][m.group(1)]["per_seed"]["stride"]
            return _pm(_stats(_dig(r, "overall", "relative_error") for r in ps), 3)
        m = re.fullmatch(r"growth_(\w+)", cid)
        if m:
            runs = summary["horizon"]["per_run"][m.group(1)]
            g = lambda k: _stats(_growth({"state": {"per_horizon": r["per_horizon"]}})
                                 for r in runs[k])
            return f"ONN {_pm(g('onn'))}; DeLaN {_pm(g('delan'))}"
        if cid.startswith("allocation_"):
            a = summary["allocation"]["share"]
            return f"free {_pm(a['free'], 1, pct=True)}; impacts {_pm(a['contact'], 1, pct=True)}"
        m = re.fullmatch(r"phase_w1_vs_(\w+)", cid)
        if m:
            ps = summary["phase"]["per_seed"]
            w = lambda k: {i: _dig(p, k, "w1_near") for i, p in enumerate(ps)}
            return "per seed " + _ratio_text(seed_ratio(w("stride"), w(m.group(1))), None,
                                             m.group(1))
        if cid == "phase_beats_any_deterministic":
            return _pm(summary["phase"]["models"]["stride"]["w1_near_over_floor"], 3)
        if cid == "nfe_delan_level":
            n = summary["nfe"]
            parts = [f"DeLaN {n['delan']['error_mean']:.3g} ± {n['delan']['error_std']:.3g}"]
            for k, c in n["curves"].items():
                parts.append(f"{NAMES.get(k, k)}: " + ", ".join(
                    f"NFE {a} {e:.3g} ± {s:.3g}" for a, e, s in
                    zip(c["nfe"], c["error_mean"], c["error_std"])))
            return "error over seeds: " + "; ".join(parts)
    except (KeyError, TypeError, ValueError, IndexError, AttributeError, ZeroDivisionError):
        return None
    return None


HEADLINE_SUMMARY = [  # (claim id, text, paper location)
    ("nfe_rate", "CFM's residual sampler faster than DDPM's at every common NFE", WHERE_NFE),
    ("nfe_delan_level", "CFM reaches DeLaN's rollout error with fewer NFEs than DDPM", WHERE_NFE),
    ("nfe_matched", "at the smallest NFE within 5% of its own best error, CFM samples faster "
     "than DDPM ([NFE, error, calls/s]: CFM, DDPM)", WHERE_NFE),
    ("allocation_free", "residual share in free swing small (<= 15%)", WHERE_ALLOCATION),
    ("allocation_contact", "residual share at impacts large (>= 50%)", WHERE_ALLOCATION),
    ("allocation_split", "residual share lower in free swing than at impacts",
     WHERE_ALLOCATION),
    ("phase_w1_vs_delan", "pendulum near upright: STRIDE's one-step distribution closer to the "
     "truth than DeLaN's (W1 ratio < 1)", WHERE_PHASE),
    ("phase_w1_vs_onn", "pendulum near upright: STRIDE closer to the truth than ONN (W1 ratio "
     "< 1)", WHERE_PHASE),
    ("phase_beats_any_deterministic", "pendulum near upright: STRIDE's W1 below the floor of "
     "any deterministic model (W1 / floor < 1)", WHERE_PHASE),
]


def summary_rows(summary: dict | None, path: pathlib.Path | None, tag: str | None,
                 rel) -> tuple[list[Row], list[str]]:
    src = "missing" if path is None else f"{rel(path)} ({tag} preset" + (
        ", pipeline check only)" if tag != "paper" else ")")
    if summary is None:
        rows = [Row(text, where, _any(_paper_of(cid)), "not run", NOT_RUN, src)
                for cid, text, where in HEADLINE_SUMMARY]
        return rows, ["## Figures (`experiments/reproduce.py`)", "",
                      "Not run: no `results/reproduce/*/summary.json`.", ""]
    claims, note = summary_claims(summary)
    by_id = {c["id"]: c for c in claims}
    cmds = summary.get("commands") or {}
    rows = []
    for cid, text, where in HEADLINE_SUMMARY:
        c = by_id.get(cid)
        if c is None:
            rows.append(Row(text, where, _any(_paper_of(cid)), "not run", NOT_RUN, src))
            continue
        spread = claim_spread(summary, cid)
        ours = _any(c["ours"]) + (f"; {spread}" if spread else "")
        rows.append(Row(text, where, _any(c["paper"]), ours, verdict(c["holds"]), src,
                        cmds.get(c.get("where"))))
    return rows, summary_section(summary, path, tag, claims, note, rel)


def _paper_of(cid: str):
    return {"nfe_rate": True, "nfe_delan_level": "CFM < DDPM", "nfe_matched": "CFM faster",
            "allocation_free": PAPER_ALLOCATION[0], "allocation_contact": PAPER_ALLOCATION[1],
            "allocation_split": list(PAPER_ALLOCATION)}.get(cid, "< 1 (qualitative)")


FIGURES = [("phase", "Phase portrait near the upright (pendulum)"),
           ("allocation", "Residual allocation (bouncing pendulum)"),
           ("nfe", "NFE trade-off (Go1)"), ("horizon", "Rollout error vs horizon (Go1, G1)")]


def summary_section(summary: dict, path: pathlib.Path, tag: str, claims: list[dict], note: str,
                    rel) -> list[str]:
    lines = [f"## Figures (`experiments/reproduce.py`, preset `{tag}`)", ""]
    if tag != "paper":
        lines += [f"> **WARNING: these figures and claims come from the `{tag}` preset** "
                  "(tiny datasets and models trained for a few hundred steps). They test the "
                  "pipeline; their numbers and verdicts say nothing about the paper. The `paper` "
                  "preset's summary (`results/reproduce/paper/summary.json` or "
                  "`results/reproduce/summary.json` tagged `paper`) is not on disk.", ""]
    git = _git_note(path)
    lines += [f"`{rel(path)}`{' (' + git + ')' if git else ''}; device: "
              f"{summary.get('device', '?')}; {note}.", ""]
    cmds = summary.get("commands") or {}
    base = path.parent
    figs = []
    for part, title in FIGURES:
        f = _dig(summary, part, "figure")
        if f:
            figs.append((part, title, base / f))
    for robot, t in (_dig(summary, "forces", "robots") or {}).items():
        if t.get("figure"):
            figs.append(("forces", f"Contact forces ({ROBOT_NAMES.get(robot, robot)})",
                         base / t["figure"]))
    for part, title, f in figs:
        seen = f.is_file()
        link = f"[{f.name}]({rel(f)})" if seen else f"{f.name} (file missing)"
        lines.append(f"- {title}: {link}; command: `{cmds.get(part, 'not recorded')}`")
        if seen:
            lines.append(f"\n  ![{title}]({rel(f)})\n")
    missing = {p: _dig(summary, p, "missing_runs") for p in ("nfe", "horizon", "forces")}
    missing = {p: m for p, m in missing.items() if m}
    if missing:
        lines += ["", "Runs missing from the figures: " + "; ".join(
            f"{p}: {', '.join(map(str, m))}" for p, m in missing.items())]
    lines += ["", "Every claim of `summary.json` (criteria in `stride_paper/claims.py`):", ""]
    rows = []
    for c in claims:
        spread = claim_spread(summary, c["id"])
        rows.append([c["id"], c["claim"], _any(c["paper"]),
                     _any(c["ours"]) + (f"; {spread}" if spread else ""), verdict(c["holds"])])
    lines += _table(["id", "claim", "paper", "ours", "verdict"], rows)
    return lines + [""]


# ---------------------------------------------------------------------------------- report

REGENERATE = [
    ("Table I (GPU; resumable)", "python experiments/table1.py --robot go1,g1 --preset paper "
     "--root R"),
    ("figures, paper preset (GPU, same root)", "python experiments/reproduce.py --preset paper "
     "--root R"),
    ("figures, tiny preset (CPU pipeline check, ~8 min)", "python experiments/reproduce.py "
     "--preset tiny --root /tmp/repro"),
    ("MPPI latency, CPU / GPU", "stride bench-mppi --preset target; stride bench-mppi --preset "
     "gpu"),
    ("this report (reads only files under results/)", "python experiments/report.py  "
     "# make report"),
]


def build(results: str | os.PathLike = "results", out: str | os.PathLike | None = None) -> dict:
    """Reads the result files and returns ``{"markdown": str, "rows": [Row]}``."""
    results = pathlib.Path(results)
    out = pathlib.Path(out) if out else results / "REPORT.md"
    base = out.parent

    def rel(p: pathlib.Path) -> str:
        return pathlib.Path(os.path.relpath(p, base)).as_posix()

    tables = {robot: load_table1(results, robot) for robot in ROBOTS}
    t_rows, t_lines = table1_rows(tables, rel)
    spath, tag = find_summary(results)
    summary = _load_json(spath) if spath else None
    s_rows, s_lines = summary_rows(summary, spath, tag, rel)
    m_rows, m_lines = mppi_rows(results, rel)
    c_rows, c_lines = closed_loop_rows(results, rel)
    rows = t_rows + s_rows + m_rows + c_rows
    counts = {v: sum(r.verdict == v for r in rows) for v in (HOLDS, FAILS, NOT_MEASURABLE,
                                                             NOT_RUN)}
    lines = ["# STRIDE on our data: the paper's claims and ours", "",
             "Generated by `python experiments/report.py` from the result files named below; "
             "do not edit by hand. The paper is `../shared/paper/stride.tex` (locations give its "
             "line numbers). Verdicts are computed from the numbers: *holds* / *does not hold* "
             "when measured, *not run* when the input is absent, *not measurable* when the runs "
             "give no finite number.", "",
             f"Verdicts over {len(rows)} claims: "
             + ", ".join(f"{n} {v}" for v, n in counts.items()) + ".", ""]
    tiny = [str(i + 1) for i, r in enumerate(rows) if "pipeline check" in r.source]
    if tiny:
        lines[-2] += (f" Of these, claims {', '.join(tiny)} rest on the `{tag}` preset "
                      "(pipeline check, not the paper).")
    if tag != "paper":
        lines += [f"> **The figure claims (NFE, allocation, phase portrait) use the "
                  f"`{tag or 'missing'}` reproduce preset**" + (
                      ": numbers that test the pipeline, not the paper." if tag else
                      ": not run.") + " Table I comes from the paper-size runs of "
                  "`results/table1/<robot>/table.json`.", ""]
    lines += ["## Claims and verdicts", ""]
    lines += _table(["#", "claim", "paper (where)", "ours", "verdict", "source"],
                    [[i + 1, r.claim, f"{r.paper} — {r.where}", r.ours, f"**{r.verdict}**",
                      r.source] for i, r in enumerate(rows)])
    cmds = list(dict.fromkeys(r.command for r in rows if r.command))
    lines += ["", "Commands that produced these numbers (from the files' `command` fields):", ""]
    lines += [f"- `{c}`" for c in cmds] + [""]
    lines += t_lines + further_section(further_tables(results), rel)
    lines += s_lines + m_lines + c_lines + gap_lines(results, rel)
    lines += ["## How to regenerate", "",
              "`R` is a data and runs folder; the GPU steps fit 10-minute calls by resuming "
              "(`--minutes`, `--parts`; see `docs/reproduce.md`). Each section's inputs are one "
              "folder of `results/` whose `README.md` gives the exact commands "
              "(`results/README.md` is the index).", ""]
    lines += [f"- {what}: `{cmd}`" for what, cmd in REGENERATE]
    return {"markdown": "\n".join(lines) + "\n", "rows": rows}


def write(results: str | os.PathLike = "results",
          out: str | os.PathLike | None = None) -> dict:
    results = pathlib.Path(results)
    out = pathlib.Path(out) if out else results / "REPORT.md"
    rep = build(results, out)
    atomic_write_text(out, rep["markdown"])
    rep["path"] = out
    return rep
