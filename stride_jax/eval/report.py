"""``results/REPORT.md``: each claim of the paper, its number, ours and a computed verdict.

Built only from result files on disk (paths relative to the results folder):

* ``go1/table.json``, ``g1/table.json`` (required): Table I, every run per seed
  (``experiments/table1.py``);
* ``reproduce/<preset>/summary.json``: the figures' numbers (``experiments/reproduce.py``); the
  ``paper`` preset is preferred (``reproduce/paper/`` or ``reproduce/summary.json`` tagged
  ``paper``), else ``tiny``, whose numbers test the pipeline and say nothing about the paper;
* ``bench_mppi_cpu.json``, ``bench_mppi_gpu.json`` (and ``*/bench_mppi_*.json``): MPPI latency
  (``stride bench-mppi``) against the issue-4 targets;
* ``closed_loop*/**/*.json``: closed-loop MPPI runs (``stride_jax.control.closed_loop``);
* ``gap_bench.json``: a pointer to the gap tool's benchmark.

The paper's numbers are the constants below, each with where it is in ``stride.tex``. Every
verdict is computed from the numbers: ``holds`` / ``does not hold`` when measured, ``not run``
when the input is absent, ``not measurable`` when the runs exist but give no finite number (e.g.
every rollout diverged). Spread is the std over seeds (population std, as ``eval/table.py``).
"""

from __future__ import annotations

import json
import math
import os
import pathlib
import re
import subprocess
from typing import Any, Iterable

from stride_jax.io import atomic_write_text

HOLDS, FAILS, NOT_RUN, NOT_MEASURABLE = "holds", "does not hold", "not run", "not measurable"

# ------------------------------------------------------------------------- the paper's numbers
# Locations: section and line numbers of /work/shared/paper/stride.tex (../shared/paper/).
TEX = "stride.tex"
WHERE_ABSTRACT = f"abstract ({TEX} l. 50)"
WHERE_TABLE1 = f"Table I, tab:hardware_results ({TEX} l. 413-437)"
WHERE_TEXT_STATE = f"Sec. IV-C, Long-Horizon Prediction ({TEX} l. 360)"
WHERE_GROWTH = f"Sec. IV-C and Fig. rollout error ({TEX} l. 358, 362-367)"
WHERE_FORCE_REL = f"Sec. IV-D, Contact and Force Prediction ({TEX} l. 387)"
WHERE_FORCE_30 = f"abstract (l. 50); Sec. IV-D ({TEX} l. 389)"
WHERE_NFE = f"Fig. inf and Sec. IV-E, Inference ({TEX} l. 392-397, 440-442)"
WHERE_ALLOCATION = f"Sec. III-F, Residual Allocation ({TEX} l. 291)"
WHERE_PHASE = f"Fig. phase and Sec. IV-G ({TEX} l. 406-411, 471-475)"
WHERE_MPPI = f"Sec. IV-F, Hardware and Real-Time ({TEX} l. 451)"
WHERE_CLOSED = f"Sec. IV-F and Fig. hardware ({TEX} l. 399-404, 449-466)"

# Table I (H = 30): (state RMSE, force error N); None where the paper has "NA".
PAPER_TABLE1 = {
    "go1": {"onn": (5.489, None), "diffusion": (3.521, None), "delan": (1.326, 9.4),
            "lnn_diffusion": (1.154, 8.8), "stride": (0.932, 6.7)},
    "g1": {"onn": (1.204, None), "diffusion": (0.314, None), "delan": (1.023, 17.1),
           "lnn_diffusion": (0.918, 15.4), "stride": (0.289, 12.1)},
}
# Sec. IV-C's stated reductions of STRIDE's state error (l. 360); on G1 they disagree with the
# table (G1: the table gives 76% vs ONN and 69% vs LNN + Diffusion).
PAPER_TEXT_REDUCTION = {("go1", "onn"): 0.83, ("g1", "onn"): 0.53,
                        ("go1", "lnn_diffusion"): 0.19, ("g1", "lnn_diffusion"): 0.21}
# Abstract (l. 50): "20% reduction in long-horizon prediction error and 30% reduction in contact
# force prediction error compared to deterministic residual baselines" (DeLaN: the one baseline
# with a deterministic residual). 20%: ratio <= 0.80. "Approximately 30%" (l. 389): a reduction
# of at least 25% (ratio <= 0.75); the paper's own table gives 0.71 on both robots.
ABSTRACT_STATE_MAX_RATIO = 0.80
ABSTRACT_FORCE_MAX_RATIO = 0.75
# Sec. IV-D (l. 387): force error ~13% (Go1) and ~8% (G1) of the nominal contact force.
PAPER_FORCE_RELATIVE = {"go1": 0.13, "g1": 0.08}
# Sec. III-F (l. 291): residual share of the predicted acceleration, free swing vs impacts.
PAPER_ALLOCATION = (0.065, 0.788)
# Sec. IV-F (l. 451): "STRIDE runs in 3 ms within the MPPI loop ... 50 Hz". The issue-4 targets:
# >= 50 Hz on a 2-core CPU for Go1, K=128, H=16, STRIDE (NFE <= 2); <= 3 ms on a GPU, K=1024, H=30.
PAPER_MPPI_MS, PAPER_MPPI_HZ = 3.0, 50.0
CPU_TARGET = dict(robot="go1", model="stride", K=128, H=16, max_nfe=2, min_hz=50.0)
GPU_TARGET = dict(robot="go1", model="stride", K=1024, H=30, max_nfe=2, max_ms=3.0)

ROBOTS = ("go1", "g1")
NAMES = {"stride": "STRIDE", "delan": "DeLaN", "lnn_diffusion": "LNN + Diffusion",
         "onn": "ONN (plain MLP)", "diffusion": "Pure diffusion", "oracle": "oracle",
         "nominal": "nominal"}
ROBOT_NAMES = {"go1": "Go1", "g1": "G1"}
LEARNED = ("stride", "delan", "onn", "lnn_diffusion", "diffusion")


# ------------------------------------------------------------------------------------ helpers

def verdict(ok: bool | None) -> str:
    return NOT_RUN if ok is None else (HOLDS if ok else FAILS)


def _finite(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _stats(values: Iterable) -> dict | None:
    v = [float(x) for x in values if _finite(x)]
    if not v:
        return None
    m = sum(v) / len(v)
    return {"mean": m, "std": math.sqrt(sum((x - m) ** 2 for x in v) / len(v)), "n": len(v)}


def _pm(s: dict | None, digits: int = 2, pct: bool = False, unit: str = "") -> str:
    if s is None:
        return "n/a"
    f = 100.0 if pct else 1.0
    u = "%" if pct else unit
    out = f"{f * s['mean']:.{digits}f}{u}"
    if s["n"] > 1:
        out += f" ± {f * s['std']:.{digits}f}{u}"
    return out + f" ({s['n']} seed{'s' if s['n'] != 1 else ''})"


def _num(x, digits: int = 3) -> str:
    if x is None:
        return "n/a"
    if isinstance(x, bool):
        return str(x)
    if isinstance(x, (int, float)):
        if not math.isfinite(x):
            return str(x)
        return f"{x:.{digits}g}" if abs(x) < 1e5 else f"{x:.2e}"
    return str(x)


def _any(x) -> str:
    """A JSON value (claim's paper/ours) in a table cell."""
    if isinstance(x, dict):
        if set(x) == {"table", "note"}:
            return _num(x["table"]) + (f" ({x['note']})" if x.get("note") else "")
        return "; ".join(f"{k}: {_any(v)}" for k, v in x.items())
    if isinstance(x, (list, tuple)):
        return "[" + ", ".join(_any(v) for v in x) + "]"
    return _num(x)


def _cell(s: str) -> str:
    return str(s).replace("|", "\\|").replace("\n", " ")


def _dig(d, *path):
    for k in path:
        if isinstance(d, dict):
            d = d.get(k)
        elif isinstance(d, list) and isinstance(k, int) and -len(d) <= k < len(d):
            d = d[k]
        else:
            return None
        if d is None:
            return None
    return d


def _load_json(path: pathlib.Path) -> Any:
    return json.loads(path.read_text())


def _git_note(path: pathlib.Path) -> str:
    """When the file was last committed (best effort; '' outside a git checkout)."""
    try:
        r = subprocess.run(["git", "log", "-1", "--format=%h %cs", "--", path.name],
                           cwd=path.parent, capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return ""
    if r.returncode != 0:
        return ""
    return f"committed {r.stdout.strip()}" if r.stdout.strip() else "not committed"


class Row:
    """One claim: what the paper says, what we measure, the verdict and where ours came from."""

    def __init__(self, claim: str, where: str, paper: str, ours: str, verdict: str,
                 source: str, command: str | None = None):
        self.claim, self.where, self.paper, self.ours = claim, where, paper, ours
        self.verdict, self.source, self.command = verdict, source, command


def _table(headers: list[str], rows: list[list]) -> list[str]:
    out = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    out += ["| " + " | ".join(_cell(c) for c in r) + " |" for r in rows]
    return out


# ---------------------------------------------------------------------------------- Table I

def load_table1(results: pathlib.Path, robot: str) -> dict:
    path = results / robot / "table.json"
    if not path.is_file():
        raise FileNotFoundError(
            f"Table I input missing: {path} (make it with `python experiments/table1.py "
            f"--robot {robot} --preset paper`, which writes results/{robot}/table.json)")
    d = _load_json(path)
    if not isinstance(d, dict) or not isinstance(d.get("runs"), list):
        raise ValueError(f"{path}: not a Table I file (expected a 'runs' list, as written by "
                         "stride_jax.eval.table)")
    d["_path"] = path
    return d


def _per_seed(t: dict, model: str, fn) -> dict[int, float]:
    out = {}
    for r in t["runs"]:
        if r.get("model") == model:
            v = fn(r)
            out[int(r.get("seed", len(out)))] = float(v) if _finite(v) else math.nan
    return out


def _state(r):
    return _dig(r, "state", "mean")


def _force(r):
    return _dig(r, "force", "mean")


def _force_rel(r):
    f, n = _dig(r, "force", "mean"), _dig(r, "force", "mean_true_normal")
    return f / n if _finite(f) and _finite(n) and n else None


def _growth(r):
    ph = _dig(r, "state", "per_horizon")
    if not ph or len(ph) < 2:
        return None
    a, b = ph[-1], ph[len(ph) // 2 - 1]
    return a / b if _finite(a) and _finite(b) and b else None


def seed_ratio(num: dict[int, float], den: dict[int, float]) -> dict:
    """STRIDE / baseline per seed (seeds paired); which seeds had a non-finite side."""
    seeds = sorted(set(num) & set(den))
    ratios = {s: num[s] / den[s] for s in seeds
              if _finite(num[s]) and _finite(den[s]) and den[s] != 0}
    return {"ratios": ratios, "seeds": seeds, "stats": _stats(ratios.values()),
            "num_bad": [s for s in seeds if not _finite(num[s])],
            "den_bad": [s for s in seeds if not _finite(den[s])]}


def _ratio_text(r: dict, threshold: float | None = None, other: str = "baseline") -> str:
    s = r["stats"]
    if s is None:
        txt = "no finite pair of seeds"
    else:
        txt = f"{s['mean']:.2f}" + (f" ± {s['std']:.2f}" if s["n"] > 1 else "")
        txt += f" ({s['n']} of {len(r['seeds'])} seeds"
        if threshold is not None:
            txt += f"; {sum(v <= threshold for v in r['ratios'].values())} meet it"
        txt += ")"
    if r["den_bad"]:
        txt += f"; {other} diverged on seed(s) {', '.join(map(str, r['den_bad']))}"
    if r["num_bad"]:
        txt += f"; STRIDE diverged on seed(s) {', '.join(map(str, r['num_bad']))}"
    return txt


def _ratio_verdict(r: dict, threshold: float, strict: bool = False) -> str:
    s = r["stats"]
    if s is None:
        return NOT_MEASURABLE if r["seeds"] else NOT_RUN
    return verdict(s["mean"] < threshold if strict else s["mean"] <= threshold)


def _model_mean(t: dict, model: str, fn) -> dict | None:
    return _stats(_per_seed(t, model, fn).values())


def table1_rows(tables: dict[str, dict], rel) -> tuple[list[Row], list[str]]:
    """Headline rows from Table I files, and the Table I section's lines."""
    rows: list[Row] = []
    # The abstract's two ratios against DeLaN: (metric, column of PAPER_TABLE1, claim, bound).
    abstract = ((_state, 0, "30-step state error >= 20% below", "20%", ABSTRACT_STATE_MAX_RATIO,
                 WHERE_ABSTRACT),
                (_force, 1, "foot-force error ~30% below", "30%", ABSTRACT_FORCE_MAX_RATIO,
                 WHERE_FORCE_30))
    for metric, col, claim, paper_text, bound, where in abstract:
        for robot in ROBOTS:
            t = tables[robot]
            ratio = seed_ratio(_per_seed(t, "stride", metric), _per_seed(t, "delan", metric))
            p = PAPER_TABLE1[robot]["stride"][col] / PAPER_TABLE1[robot]["delan"][col]
            rows.append(Row(f"{ROBOT_NAMES[robot]}: STRIDE's {claim} DeLaN's "
                            f"(STRIDE / DeLaN <= {bound:.2f})", where,
                            f"{paper_text} (Table I: {p:.2f})", _ratio_text(ratio, bound, "DeLaN"),
                            _ratio_verdict(ratio, bound), rel(t["_path"]), t.get("command")))
    for robot in ROBOTS:
        t, src, cmd = tables[robot], rel(tables[robot]["_path"]), tables[robot].get("command")
        paper, R = PAPER_TABLE1[robot], ROBOT_NAMES[robot]
        # Lowest state error of the five.
        means = {m: _model_mean(t, m, _state) for m in LEARNED}
        means = {m: s for m, s in means.items() if s is not None}
        others = {m: s for m, s in means.items() if m != "stride"}
        p_best = min((m for m in paper if m != "stride"), key=lambda m: paper[m][0])
        if "stride" not in means or not others:
            v, ours = (NOT_RUN if not any(r.get("model") == "stride" for r in t["runs"])
                       else NOT_MEASURABLE), "n/a"
        else:
            best = min(others, key=lambda m: others[m]["mean"])
            v = verdict(means["stride"]["mean"] < others[best]["mean"])
            ours = f"STRIDE {_pm(means['stride'])}; best other {NAMES[best]} {_pm(others[best])}"
            bad = [m for m in LEARNED if any(not _finite(x) for x in
                                             _per_seed(t, m, _state).values())]
            if bad:
                ours += f" (seeds with every rollout diverged, left out: " \
                        f"{', '.join(NAMES[m] for m in bad)})"
        rows.append(Row(f"{R}: STRIDE has the lowest 30-step state RMSE of the five models",
                        WHERE_TABLE1, f"STRIDE {paper['stride'][0]}; best other "
                        f"{NAMES[p_best]} {paper[p_best][0]}", ours, v, src, cmd))
        # Lowest force error of the structured models.
        fm = {m: _model_mean(t, m, _force) for m in ("stride", "delan", "lnn_diffusion")}
        fm = {m: s for m, s in fm.items() if s is not None}
        fo = {m: s for m, s in fm.items() if m != "stride"}
        if "stride" not in fm or not fo:
            v, ours = NOT_RUN, "n/a"
        else:
            best = min(fo, key=lambda m: fo[m]["mean"])
            v = verdict(fm["stride"]["mean"] < fo[best]["mean"])
            ours = (f"STRIDE {_pm(fm['stride'], 1, unit=' N')}; best other {NAMES[best]} "
                    f"{_pm(fo[best], 1, unit=' N')}")
        rows.append(Row(f"{R}: STRIDE has the lowest foot-force error of the structured models",
                        WHERE_TABLE1, f"STRIDE {paper['stride'][1]} N; DeLaN "
                        f"{paper['delan'][1]} N, LNN + Diffusion {paper['lnn_diffusion'][1]} N",
                        ours, v, src, cmd))
    for robot in ROBOTS:
        t, src, cmd = tables[robot], rel(tables[robot]["_path"]), tables[robot].get("command")
        R = ROBOT_NAMES[robot]
        s = _model_mean(t, "stride", _force_rel)
        rows.append(Row(f"{R}: STRIDE's force error / mean stance force at most the paper's",
                        WHERE_FORCE_REL, f"{100 * PAPER_FORCE_RELATIVE[robot]:.0f}%",
                        _pm(s, 1, pct=True),
                        NOT_RUN if s is None else verdict(s["mean"] <= PAPER_FORCE_RELATIVE[
                            robot]), src, cmd))
    for robot in ROBOTS:
        t, src, cmd = tables[robot], rel(tables[robot]["_path"]), tables[robot].get("command")
        R = ROBOT_NAMES[robot]
        go, gd = _model_mean(t, "onn", _growth), _model_mean(t, "delan", _growth)
        rows.append(Row(f"{R}: ONN's error grows faster than DeLaN's (e(30) / e(15); "
                        "2 = linear from zero)", WHERE_GROWTH,
                        "ONN near-exponential, DeLaN ~linear",
                        f"ONN {_pm(go)}; DeLaN {_pm(gd)}",
                        NOT_RUN if go is None or gd is None else verdict(
                            go["mean"] > gd["mean"]), src, cmd))
    return rows, table1_section(tables, rel)


def table1_section(tables: dict[str, dict], rel) -> list[str]:
    lines = ["## Table I: open-loop accuracy (H = 30)", ""]
    for robot in ROBOTS:
        t = tables[robot]
        note = _git_note(t["_path"])
        lines += [f"`{rel(t['_path'])}`{' (' + note + ')' if note else ''}, device backend "
                  f"`{t.get('backend', '?')}`; command: `{t.get('command', 'not recorded')}`", ""]
    lines += ["Ours: mean ± std over seeds of each run's cumulative normalised 30-step "
              "observation RMSE (`eval/rollout.py`; rollouts that left the floating-point range "
              "are counted, not averaged; a seed with every rollout diverged has no number) and "
              "mean |error| of stance feet's vertical force (N). The paper's normalisation is "
              "not ours, so absolute state RMSEs are not comparable across the two columns; "
              "ratios are.", ""]
    rows = []
    for robot in ROBOTS:
        t = tables[robot]
        for m in LEARNED:
            st = _per_seed(t, m, _state)
            if not st:
                continue
            bad = [s for s, v in st.items() if not _finite(v)]
            p = PAPER_TABLE1[robot].get(m, (None, None))
            rows.append([ROBOT_NAMES[robot], NAMES[m], _num(p[0]), _pm(_stats(st.values())),
                         f"{len(bad)} of {len(st)}" if bad else "0",
                         "NA" if p[1] is None else _num(p[1]),
                         _pm(_model_mean(t, m, _force), 1) if m in (
                             "stride", "delan", "lnn_diffusion") else "NA"])
    lines += _table(["robot", "model", "paper state RMSE", "ours state RMSE",
                     "seeds all diverged", "paper force (N)", "ours force (N)"], rows)
    lines += ["", "STRIDE / baseline, per seed (seeds paired), mean ± std. 'better': ratio < 1 "
              "(the direction of the paper's table); 'margin': ratio at most the paper's "
              "table ratio.", ""]
    rows = []
    for robot in ROBOTS:
        t, paper = tables[robot], PAPER_TABLE1[robot]
        for metric, fn, k in (("state", _state, 0), ("force", _force, 1)):
            for m in ("onn", "diffusion", "delan", "lnn_diffusion"):
                if paper[m][k] is None:
                    continue
                r = seed_ratio(_per_seed(t, "stride", fn), _per_seed(t, m, fn))
                if not r["seeds"]:
                    continue
                p = paper["stride"][k] / paper[m][k]
                txt = PAPER_TEXT_REDUCTION.get((robot, m)) if metric == "state" else None
                ptxt = f"{p:.2f}" + (f" (text: {100 * txt:.0f}% lower)" if txt else "")
                rows.append([ROBOT_NAMES[robot], metric, NAMES[m], ptxt,
                             _ratio_text(r, None, NAMES[m]), _ratio_verdict(r, 1.0, True),
                             _ratio_verdict(r, p)])
    lines += _table(["robot", "metric", "STRIDE / ...", "paper", "ours", "better", "margin"],
                    rows)
    return lines + [""]


# ------------------------------------------------------------------------ reproduce summary

def find_summary(results: pathlib.Path) -> tuple[pathlib.Path | None, str | None]:
    """The paper preset's summary.json if present, else the tiny preset's, else (None, None)."""
    rep = results / "reproduce"
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
    ``figures.claims``); a note says when a stored verdict differs or recomputing failed."""
    stored = {c.get("id"): c.get("holds") for c in summary.get("claims") or []}
    try:
        from stride_jax.eval import figures
        claims = figures.claims(summary)
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
            if other is None:  # the best baseline by mean, as figures.claims
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
    lines += ["", "Every claim of `summary.json` (criteria in `stride_jax/eval/figures.py`):", ""]
    rows = []
    for c in claims:
        spread = claim_spread(summary, c["id"])
        rows.append([c["id"], c["claim"], _any(c["paper"]),
                     _any(c["ours"]) + (f"; {spread}" if spread else ""), verdict(c["holds"])])
    lines += _table(["id", "claim", "paper", "ours", "verdict"], rows)
    return lines + [""]


# ---------------------------------------------------------------------------------- MPPI

def load_bench(results: pathlib.Path, kind: str) -> list[tuple[pathlib.Path, dict]]:
    out = []
    for p in [results / f"bench_mppi_{kind}.json", *sorted(results.glob(
            f"*/**/bench_mppi_{kind}.json"))]:
        if p.is_file():
            out.append((p, _load_json(p)))
    return out


def _bench_match(rows: list[dict], target: dict) -> list[dict]:
    return [r for r in rows if r.get("robot") == target["robot"]
            and r.get("model") == target["model"] and r.get("K") == target["K"]
            and r.get("H") == target["H"] and (r.get("nfe") or 0) <= target["max_nfe"]
            and _finite(r.get("ms"))]


def _net(bench: dict) -> str:
    """``hidden x depth`` of a bench file's networks."""
    return f"{_dig(bench, 'env', 'config', 'hidden')} x {_dig(bench, 'env', 'config', 'depth')}"


def mppi_rows(results: pathlib.Path, rel) -> tuple[list[Row], list[str]]:
    rows, lines = [], ["## MPPI step latency (`stride bench-mppi`)", ""]
    for kind, target in (("cpu", CPU_TARGET), ("gpu", GPU_TARGET)):
        files = load_bench(results, kind)
        found = [(p, d, r) for p, d in files for r in _bench_match(d.get("rows") or [], target)]
        if kind == "cpu":
            claim = (f"MPPI replans at >= {target['min_hz']:.0f} Hz on a 2-core CPU (Go1, "
                     f"K={target['K']}, H={target['H']}, STRIDE, NFE <= {target['max_nfe']})")
            paper = f"{PAPER_MPPI_HZ:.0f} Hz on board (issue-4 target)"
        else:
            claim = (f"MPPI step <= {target['max_ms']:.0f} ms on a GPU (Go1, K={target['K']}, "
                     f"H={target['H']}, STRIDE)")
            paper = f"{PAPER_MPPI_MS:.0f} ms (issue-4 target)"
        if not found:
            rows.append(Row(claim, WHERE_MPPI, paper, "not run" if not files else
                            "no matching row", NOT_RUN,
                            ", ".join(rel(p) for p, _ in files) or "missing"))
        else:
            p, d, best = min(found, key=lambda x: x[2]["ms"])
            ok = (1000.0 / best["ms"] >= target["min_hz"]) if kind == "cpu" else (
                best["ms"] <= target["max_ms"])
            others = [f"{r['ms']:.1f} ms ({_net(e)}, {r.get('substeps')} substeps, {rel(q)})"
                      for q, e, r in found if r is not best]
            ours = (f"{best['ms']:.1f} ms = {1000 / best['ms']:.1f} Hz (fastest matching row: "
                    f"networks {_net(d)}, {best.get('substeps')} substep(s) per control step, "
                    f"NFE {best.get('nfe')}, {_dig(d, 'env', 'device')})"
                    + (f"; also {', '.join(others)}" if others else ""))
            rows.append(Row(claim, WHERE_MPPI, paper, ours, verdict(ok), rel(p),
                            _dig(d, "env", "command")))
        for p, d in files:
            env = d.get("env") or {}
            git = _git_note(p)
            lines += [f"`{rel(p)}`{' (' + git + ')' if git else ''}: `{env.get('command')}` on "
                      f"{env.get('device')} (jax {env.get('jax')}), networks {_net(d)}; median of "
                      f"{_dig(env, 'config', 'repeats')} jitted planning steps; "
                      "floor = the FLOP floor at the machine's measured peak.", ""]
            lines += _table(["robot", "model", "K", "H", "substeps", "NFE", "ms", "Hz",
                             "x floor"],
                            [[r.get("robot"), r.get("model"), r.get("K"), r.get("H"),
                              r.get("substeps"), r.get("nfe") or "-", _num(r.get("ms")),
                              _num(r.get("hz")), _num(r.get("ratio"))]
                             for r in d.get("rows") or []])
            lines.append("")
    if len(lines) == 2:
        lines += ["Not run: no `bench_mppi_*.json`.", ""]
    return rows, lines


# ----------------------------------------------------------------------------- closed loop

def _row_model(r: dict) -> str:
    if r.get("model"):
        return str(r["model"])
    m = re.search(r"\(([^)]+)\)", str(r.get("mode", "")))
    return m.group(1) if m else str(r.get("mode", "?"))


def _row_key(r: dict) -> str:
    if r.get("scenario") is not None:
        return str(r["scenario"])
    if r.get("speed") is not None:
        return f"{r['speed']} m/s"
    return "-"


def load_closed_loop(results: pathlib.Path) -> list[tuple[pathlib.Path, dict]]:
    out = []
    for p in sorted(results.glob("closed_loop*/**/*.json")):
        try:
            d = _load_json(p)
        except (OSError, json.JSONDecodeError):
            continue  # being written by another job: skipped, not fatal
        if isinstance(d, dict) and isinstance(d.get("rows"), list):
            out.append((p, d))
    return out


def closed_loop_rows(results: pathlib.Path, rel) -> tuple[list[Row], list[str]]:
    files = load_closed_loop(results)
    lines = ["## Closed-loop tracking (MPPI in MJX, Go1)", ""]
    claim_fall = ("STRIDE in MPPI tracks its commands without falling (velocity steps and "
                  "changes, 20 deg slope, unseen ground)")
    claim_best = ("STRIDE's tracking at least as good as DeLaN's and ONN's in every scenario "
                  "(fewer falls, then velocity error)")
    paper_fall = "no falls on hardware (velocity 0-2 m/s, 20 deg, 4 unseen terrains)"
    paper_best = "lowest error of the compared models (hardware)"
    if not files:
        lines += ["Not yet run: no `results/closed_loop*/**/*.json`.", ""]
        return [Row(claim_fall, WHERE_CLOSED, paper_fall, "not yet run", NOT_RUN, "missing"),
                Row(claim_best, WHERE_CLOSED, paper_best, "not yet run", NOT_RUN, "missing")], \
            lines
    cells: dict[tuple, list[dict]] = {}
    for p, d in files:
        for r in d["rows"]:
            cells.setdefault((p, _row_key(r), _row_model(r)), []).append(r)
    models = sorted({m for _, _, m in cells})
    stride = {k: v for k, v in cells.items() if k[2] == "stride"}
    srcs = ", ".join(rel(p) for p, _ in files)
    cmd = "; ".join(filter(None, ((d.get("command") or _dig(d, "env", "command"))
                                  for _, d in files)))
    if not stride:
        why = f"not yet run (no STRIDE rows; models present: {', '.join(models)})"
        rows = [Row(claim_fall, WHERE_CLOSED, paper_fall, why, NOT_RUN, srcs, cmd),
                Row(claim_best, WHERE_CLOSED, paper_best, why, NOT_RUN, srcs, cmd)]
    else:
        runs = [r for v in stride.values() for r in v]
        falls = sum(bool(r.get("fell")) for r in runs)
        rows = [Row(claim_fall, WHERE_CLOSED, paper_fall,
                    f"fell in {falls} of {len(runs)} runs over {len(stride)} scenarios",
                    verdict(falls == 0), srcs, cmd)]
        # A run that falls is worse than one that stays up, whatever its error while upright
        # (measured until the fall); among equals, the lower velocity error wins.
        fell = lambda rs: sum(bool(r.get("fell")) for r in rs) / len(rs)
        comps = []
        for (p, key, _), rs in stride.items():
            s = _stats(r.get("vel_rmse") for r in rs)
            for other in ("delan", "onn"):
                os_ = cells.get((p, key, other), [])
                o = _stats(r.get("vel_rmse") for r in os_)
                if s is not None and o is not None:
                    comps.append((key, other, (fell(rs), s["mean"]) <= (fell(os_), o["mean"])))
        if comps:
            worse = [f"{k} vs {NAMES[o]}" for k, o, ok in comps if not ok]
            rows.append(Row(claim_best, WHERE_CLOSED, paper_best,
                            f"at most in {len(comps) - len(worse)} of {len(comps)} comparisons"
                            + (f" (worse: {', '.join(worse)})" if worse else ""),
                            verdict(not worse), srcs, cmd))
        else:
            rows.append(Row(claim_best, WHERE_CLOSED, paper_best,
                            "no scenario with STRIDE and DeLaN or ONN side by side", NOT_RUN,
                            srcs, cmd))
    for p, d in files:
        c = d.get("command") or _dig(d, "env", "command")
        git = _git_note(p)
        lines += [f"`{rel(p)}`{' (' + git + ')' if git else ''}: `{c}`; "
                  f"device {d.get('device') or _dig(d, 'env', 'device')}. Cells: velocity "
                  "tracking RMSE (m/s), mean ± std over runs; falls.", ""]
        keys = list(dict.fromkeys(_row_key(r) for r in d["rows"]))
        ms = list(dict.fromkeys(_row_model(r) for r in d["rows"]))
        table = []
        for k in keys:
            row = [k]
            for m in ms:
                rs = cells.get((p, k, m), [])
                s = _stats(r.get("vel_rmse") for r in rs)
                fell = sum(bool(r.get("fell")) for r in rs)
                row.append("-" if not rs else (f"{s['mean']:.2f}" if s else "n/a") + (
                    f" ± {s['std']:.2f}" if s and s["n"] > 1 else "") + (
                    f", fell {fell}/{len(rs)}" if fell else ""))
            table.append(row)
        lines += _table(["scenario"] + ms, table) + [""]
    return rows, lines


# ------------------------------------------------------------------------------- gap bench

def gap_lines(results: pathlib.Path, rel) -> list[str]:
    p = results / "gap_bench.json"
    lines = ["## Sim-to-real gap tool (`stride gap`)", ""]
    if not p.is_file():
        return lines + ["Not run: no `results/gap_bench.json`.", ""]
    d = _load_json(p)
    md = p.with_suffix(".md")
    lines.append(f"Not a claim of the paper. `{rel(p)}` (command `{d.get('command')}`"
                 + (f"; details in [{md.name}]({rel(md)})" if md.is_file() else "") + "):")
    for k, s in (d.get("summary") or {}).items():
        lines.append(f"- {k}: top-1 attribution of single planted effects "
                     f"{_num(s.get('top1_single'))}, of pairs {_num(s.get('top1_pairs'))}, "
                     f"confident false attributions {s.get('confident_false_attributions')} "
                     f"({s.get('cases')} cases)")
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
                  "`results/<robot>/table.json`.", ""]
    lines += ["## Claims and verdicts", ""]
    lines += _table(["#", "claim", "paper (where)", "ours", "verdict", "source"],
                    [[i + 1, r.claim, f"{r.paper} — {r.where}", r.ours, f"**{r.verdict}**",
                      r.source] for i, r in enumerate(rows)])
    cmds = list(dict.fromkeys(r.command for r in rows if r.command))
    lines += ["", "Commands that produced these numbers (from the files' `command` fields):", ""]
    lines += [f"- `{c}`" for c in cmds] + [""]
    lines += t_lines + s_lines + m_lines + c_lines + gap_lines(results, rel)
    lines += ["## How to regenerate", "",
              "`R` is a data and runs folder; the GPU steps fit 10-minute calls by resuming "
              "(`--minutes`, `--parts`; see `docs/reproduce.md`).", ""]
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
