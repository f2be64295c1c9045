"""The report's control sections: MPPI latency against the issue-4 targets, closed-loop runs
and the gap tool's benchmark.
"""

from __future__ import annotations

import json
import pathlib
import re

from stride_paper.report_common import (
    CPU_TARGET, GPU_TARGET, MPPI, NAMES, NOT_RUN, PAPER_MPPI_HZ, PAPER_MPPI_MS, WHERE_CLOSED,
    WHERE_MPPI,
    Row, _dig, _finite, _git_note, _load_json, _num, _stats, _table, verdict,
)
from stride_paper.seeds import (at_most, fall_rates_differ, headline_picks, in_headline,
                                kind_and_seed, seed_means, welch)

# ---------------------------------------------------------------------------------- MPPI

def load_bench(results: pathlib.Path, kind: str) -> list[tuple[pathlib.Path, dict]]:
    out = []
    folder = results / MPPI
    main = folder / f"bench_mppi_{kind}.json"
    for p in [main, *sorted(q for q in folder.glob(f"*/**/bench_mppi_{kind}.json") if q != main)]:
        if p.is_file():
            out.append((p, _load_json(p)))
    return out


def _bench_match(rows: list[dict], target: dict) -> list[dict]:
    return [r for r in rows if r.get("robot") == target["robot"]
            and r.get("model") == target["model"] and r.get("K") == target["K"]
            and r.get("H") == target["H"] and (r.get("nfe") or 0) <= target["max_nfe"]
            and _finite(r.get("ms"))]


def _net(bench: dict) -> str:
    """``hidden x depth`` of a bench file's networks, whether L and V share one, the fused
    kernels they ran as (if any) and the number of devices the samples were split over."""
    net = f"{_dig(bench, 'env', 'config', 'hidden')} x {_dig(bench, 'env', 'config', 'depth')}"
    if _dig(bench, "env", "config", "shared_lnn"):
        net += ", one network for L and V"
    kernel = _dig(bench, "env", "config", "kernel")
    if kernel and kernel != "xla":
        net += f", fused kernels ({kernel})"
    n_devices = _dig(bench, "env", "n_devices") or 1
    return net + (f", {n_devices} devices" if n_devices > 1 else "")


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


def _worse(key: str, other: str, w: dict | None, falls: tuple[int, int, int, int]) -> str:
    """One comparison STRIDE loses: the scenario and the other kind; lost on falls (``falls``:
    STRIDE's falls and runs, the other's), their counts; else (where both have several trained
    seeds) STRIDE's margin, Welch's 90% interval and whether the seeds tell the kinds apart."""
    if fall_rates_differ(*falls):
        a, n, b, m = falls
        return f"{key} vs {NAMES[other]}: fell {a} of {n} against {b} of {m}"
    if w is None:
        return f"{key} vs {NAMES[other]}"
    apart = "told apart" if w["lo"] > 0 else "not told apart"
    return (f"{key} vs {NAMES[other]} by {w['diff']:.4f} m/s, 90% [{w['lo']:+.4f}, "
            f"{w['hi']:+.4f}] over {w['n'][0]} / {w['n'][1]} trained seeds: {apart}")


def _claim_cells(files: list[tuple[pathlib.Path, dict]]) -> tuple[dict, list, str]:
    """The closed-loop claims' cells ``(file, scenario, model) -> rows``: where a merged table
    names its ``headline`` parts (the current planner: ``stride_jax.jobs.closed_loop.merge``),
    those parts' rows only, every trained seed and planner draw under its model kind, and no
    other file's; otherwise every row of every file under its own name (the history)."""
    heads = [(p, d) for p, d in files if isinstance(d.get("headline"), dict)]
    cells: dict[tuple, list[dict]] = {}
    if not heads:
        for p, d in files:
            for r in d["rows"]:
                cells.setdefault((p, _row_key(r), _row_model(r)), []).append(r)
        return cells, files, ""
    for p, d in heads:
        picks = headline_picks(d) or {}
        for r in d["rows"]:
            if in_headline(r, picks):
                cells.setdefault((p, _row_key(r), kind_and_seed({"model": _row_model(r)})[0]),
                               []).append(r)
    return cells, heads, "; the current planner: " + "; ".join(
        f"{', '.join(d['headline'].get('parts') or [])} of {p.parent.name}" for p, d in heads)


MAX_PART_COMMANDS = 4  # a merged table's commands written out in full; above: where they are


def _command(d: dict, headline: bool = False) -> str | None:
    """A run's command; a merged table's part commands joined: with ``headline`` its headline's
    parts' alone (what the claims read), else every part's, or None where there are more than
    :data:`MAX_PART_COMMANDS` (a merged table is the history of every planner tried: tens of
    parts; :func:`_commands_kept` says where they are)."""
    parts = d.get("parts")
    if not isinstance(parts, dict):
        return d.get("command") or _dig(d, "env", "command")
    head = headline_picks(d) or {}
    names = [n for n in parts if n in head] if headline and head else list(parts)
    if not headline and len(names) > MAX_PART_COMMANDS:
        return None
    return " ; ".join(str(parts[n].get("command", "")) for n in names) or None


def _commands_kept(d: dict) -> str:
    """Where a table's commands are when :func:`_command` does not write them out."""
    if not isinstance(d.get("parts"), dict):
        return "no command recorded"
    return (f"merged from {len(d['parts'])} parts (`experiments/closed_loop_merge.py`), "
            "each part's command kept in the file under `parts`")


def _part_devices(d: dict) -> str | None:
    parts = d.get("parts")
    if isinstance(parts, dict):
        return ", ".join(dict.fromkeys(str(v.get("device")) for v in parts.values()))
    return None


def load_closed_loop(results: pathlib.Path) -> list[tuple[pathlib.Path, dict]]:
    out = []
    for p in sorted(results.glob("closed_loop*/**/*.json")):
        if "parts" in p.relative_to(results).parts:
            continue  # a merged table's parts (stride_jax.jobs.closed_loop.merge): read merged
        try:
            d = _load_json(p)
        except (OSError, json.JSONDecodeError):
            continue  # being written by another job: skipped, not fatal
        # a closed-loop table's rows carry the tracking error; other tables kept beside them
        # (a probe's falls per noise level) have rows too, and are not closed-loop rows
        rows = d.get("rows") if isinstance(d, dict) else None
        if isinstance(rows, list) and all(isinstance(r, dict) and "vel_rmse" in r for r in rows):
            out.append((p, d))
    return out


def slope_unseen(d: dict, r: dict) -> bool:
    """Whether row ``r`` of closed-loop table ``d`` is on an emulated slope (``slope*``,
    ``tilt*``: gravity tilted under a level floor) with a controller that read world down, not
    the slope: runs whose config has no ``sense_gravity`` (before session 46) or has it off."""
    if not str(r.get("scenario", "")).startswith(("slope", "tilt")):
        return False
    parts = d.get("parts") if isinstance(d.get("parts"), dict) else {}
    env = parts.get(r.get("part")) or d.get("env") or {}
    return not (env.get("config") or {}).get("sense_gravity", False)


def closed_loop_rows(results: pathlib.Path, rel) -> tuple[list[Row], list[str]]:
    files = load_closed_loop(results)
    lines = ["## Closed-loop tracking (MPPI in MJX, Go1 and G1)", ""]
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
    claim_cells, claim_files, current = _claim_cells(files)
    models = sorted({m for _, _, m in claim_cells})
    stride = {k: v for k, v in claim_cells.items() if k[2] == "stride"}
    srcs = ", ".join(rel(p) for p, _ in claim_files)
    cmd = "; ".join(filter(None, (_command(d, headline=True) for _, d in claim_files)))
    if not stride:
        why = f"not yet run (no STRIDE rows; models present: {', '.join(models)})"
        rows = [Row(claim_fall, WHERE_CLOSED, paper_fall, why, NOT_RUN, srcs, cmd),
                Row(claim_best, WHERE_CLOSED, paper_best, why, NOT_RUN, srcs, cmd)]
    else:
        # a run that falls is worse than one that stays up (stride_paper.seeds.at_most)
        falls = lambda rs: sum(bool(r.get("fell")) for r in rs)
        runs = [r for v in stride.values() for r in v]
        tables = {p: d for p, d in claim_files}
        unseen = sum(slope_unseen(tables[p], r) for (p, _, _), v in stride.items() for r in v)
        hidden = (f"; {unseen} of these runs are on slopes their controller could not sense "
                  "(world-down gravity, before session 46: results/planning_diagnosis/README.md)"
                  if unseen else "")
        rows = [Row(claim_fall, WHERE_CLOSED, paper_fall,
                    f"fell in {falls(runs)} of {len(runs)} runs over {len(stride)} scenarios"
                    f"{hidden}{current}", verdict(falls(runs) == 0), srcs, cmd)]
        comps = []
        for (p, key, _), rs_all in stride.items():
            for other in ("delan", "onn"):
                # side by side: a headline's parts are one planner (what the headline declares,
                # each model may have run in its own part); else the parts (runs) that hold both
                # (a merged table's rows name theirs)
                os_all = claim_cells.get((p, key, other), [])
                if current:
                    rs, os_ = rs_all, os_all
                else:
                    both = {r.get("part") for r in rs_all} & {r.get("part") for r in os_all}
                    rs = [r for r in rs_all if r.get("part") in both]
                    os_ = [r for r in os_all if r.get("part") in both]
                s = _stats(r.get("vel_rmse") for r in rs)
                o = _stats(r.get("vel_rmse") for r in os_)
                if rs and os_ and s is not None and o is not None:
                    where = f" ({p.parent.name})" if len(claim_files) > 1 else ""
                    # STRIDE minus the other over trained seeds (each one draw of its
                    # training): whether they tell the two apart
                    w = welch(seed_means(rs).values(), seed_means(os_).values())
                    counts = (falls(rs), len(rs), falls(os_), len(os_))
                    comps.append((key + where, other,
                                  at_most(*counts[:2], s["mean"], *counts[2:], o["mean"]), w,
                                  counts))
        if comps:
            worse = [(k, o, w, c) for k, o, ok, w, c in comps if not ok]
            # lost on falls: counted apart (the seeds' interval is of the upright error)
            on_falls = [x for x in worse if fall_rates_differ(*x[3])]
            on_error = [x for x in worse if x not in on_falls]
            apart = [x for x in on_error if x[2] is not None and x[2]["lo"] > 0]
            seeded = [x for x in on_error if x[2] is not None]
            rows.append(Row(claim_best, WHERE_CLOSED, paper_best,
                            f"at most in {len(comps) - len(worse)} of {len(comps)} comparisons"
                            + (f"; {len(on_falls)} worse on falls" if on_falls else "")
                            + (f"; of the {len(on_error)} worse in velocity error, {len(apart)} "
                               "told apart by the trained seeds (Welch's 90% interval of STRIDE "
                               f"minus the other clear of 0), {len(seeded) - len(apart)} not"
                               + (f", {len(on_error) - len(seeded)} without seeds to tell"
                                  if len(seeded) < len(on_error) else "")
                               if seeded else "")
                            + (f" (worse: {'; '.join(_worse(*x) for x in worse)})"
                               if worse else "") + current,
                            verdict(not worse), srcs, cmd))
        else:
            rows.append(Row(claim_best, WHERE_CLOSED, paper_best,
                            "no scenario with STRIDE and DeLaN or ONN side by side", NOT_RUN,
                            srcs, cmd))
    if current:
        lines += [f"Claims 24-25 read the current planner's rows alone{current} (a merged table's "
                  "`headline`); every table below, the history of every planner tried, keeps "
                  "each row under its own name.", ""]
    cells: dict[tuple, list[dict]] = {}  # the tables below: every row under its own name
    for p, d in files:
        for r in d["rows"]:
            cells.setdefault((p, _row_key(r), _row_model(r)), []).append(r)
    for p, d in files:
        c = _command(d)
        git = _git_note(p)
        lines += [f"`{rel(p)}`{' (' + git + ')' if git else ''}: "
                  f"{f'`{c}`' if c else _commands_kept(d)}; "
                  f"device {d.get('device') or _dig(d, 'env', 'device') or _part_devices(d)}. "
                  "Cells: velocity tracking RMSE (m/s), mean ± std over runs; falls.", ""]
        keys = list(dict.fromkeys(_row_key(r) for r in d["rows"]))
        ms = list(dict.fromkeys(_row_model(r) for r in d["rows"]))

        def cell(k, m):
            rs = cells.get((p, k, m), [])
            s = _stats(r.get("vel_rmse") for r in rs)
            fell = sum(bool(r.get("fell")) for r in rs)
            return "-" if not rs else (f"{s['mean']:.3f}" if s else "n/a") + (
                f" ± {s['std']:.3f}" if s and s["n"] > 1 else "") + (
                f", fell {fell}/{len(rs)}" if fell else "")
        if len(ms) <= len(keys):  # one row per scenario, a column per model
            lines += _table(["scenario"] + ms, [[k] + [cell(k, m) for m in ms] for k in keys])
        else:  # a merged table's many models (and parts): a row per model, a column per scenario
            lines += _table(["model"] + keys, [[m] + [cell(k, m) for k in keys] for m in ms])
        lines.append("")
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
    q = results / "gap_bench_go1_independent.json"
    if q.is_file():  # logs from independent code and simulator settings (issue 18)
        d = _load_json(q)
        md = q.with_suffix(".md")
        lines += ["", f"On logs written by independent code with simulator settings drawn per case, `{rel(q)}` "
                  f"(command `{d.get('command')}`" + (f"; details in [{md.name}]({rel(md)})" if md.is_file() else "")
                  + "; targets: top-1 single >= 0.9, pairs >= 0.8, median shrink >= 0.8, no confident false "
                  "attribution):"]
        for k, s in (d.get("summary") or {}).items():
            lines.append(f"- {k}: top-1 single {_num(s.get('top1_single'))}, pairs {_num(s.get('top1_pairs'))}, "
                         f"median shrink of the truth's own {_num(s.get('median_shrink_single'))}, confident false "
                         f"{s.get('confident_false')}, confident partial {s.get('confident_partial')} "
                         f"({s.get('cases')} cases)")
    q = results / "gap_bench_go1_independent_controls.json"
    if q.is_file():  # the detection's level: no-effect cases with drawn simulator settings
        d = _load_json(q)
        md = q.with_suffix(".md")
        lines += ["", f"No-effect controls with drawn simulator settings, `{rel(q)}` (command `{d.get('command')}`"
                  + (f"; details in [{md.name}]({rel(md)})" if md.is_file() else "") + "):"]
        for k, s in (d.get("summary") or {}).items():
            lines.append(f"- {k}: a gap called on top of the calibrated settings in {s.get('controls_detected')} of "
                         f"{s.get('controls')}, a physical effect named in {s.get('controls_named')}, confidently "
                         f"in {s.get('confident_false')}")
    return lines + [""]


