"""Issue 19's closed-loop targets, read off each robot's merged table (its ``headline`` parts: the
current planner), in one table per robot (``OUT.md``, ``OUT.json``):

- no falls: every headline episode stays up;
- STRIDE's velocity RMSE at most the policy's in at least 3 of 4 scenarios (here: in at least
  75% of the scenarios both ran);
- at most DeLaN's and ONN's in every scenario (fewer falls first, then the mean error; the
  scenarios STRIDE is at most each in are counted too);
- at most 1/5 of the oracle's (planning through MJX) time per control step.

Beside them, the oracle's own tracking where the headline holds an oracle row of the scenario
(planning through the scenario's MJX model over the same policy and learned reward: what the
planner does with a right model); its rows over earlier policies are not read for it. A line
under each robot's targets reads that oracle as the targets read STRIDE, for reference: in how
many scenarios the same planner with a right model is at most the policy, and where STRIDE is
at most it (what "at most the policy" asks of a model where even the simulator itself is not),
and in how many comparisons it is at most DeLaN's and ONN's (whether a right model would meet
the baselines' target).

    python experiments/closed_loop_targets.py \\
        go1=results/closed_loop_go1_gpu/closed_loop.json \\
        g1=results/closed_loop_g1_gpu/closed_loop.json --out results/closed_loop_targets

A model kind's value in a scenario is the mean over its trained seeds (each the mean of its
planner draws that stayed up: ``stride_paper.seeds``); its falls count every episode. The
policy's rows are the headline's own, or ``--ROBOT-policy MODEL@PART,...`` where the headline
holds none (the first listed part holding a scenario wins); the oracle's time is the mean of the
table's oracle rows of the same scenario (any part: its time does not depend on the policy
beside it), else of all its oracle rows; its time and its tracking both only from rows at
STRIDE's samples and horizon (K, H): a scenario without such an oracle row leaves the time
target not measured rather than judged against a planner of another size. Each ratio reads
STRIDE's and the oracle's times off one card (the parts' ``device``), the worst over the cards
both ran on; an oracle only on other cards leaves the target not measured there.

``--ROBOT-timing PART,...`` takes the controllers' own times (``controller_ms``) from parts run
to time them (STRIDE's and the oracle's, ``--controller-repeats``, at the headline STRIDE's K
and H), in place of the headline's, whose rows (many episodes side by side) mostly hold only
the closed loop's; a scenario keeps the headline's where the parts lack STRIDE or the oracle.

``--ROBOT-headline ENTRY,...`` reads the targets off other rows of the same table than its
headline (entries as ``closed_loop_merge.py --headline`` takes them, checked against the table):
a candidate planner setting merged beside the headline, judged as the headline would be without
making it the headline.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

import numpy as np

from stride_jax import io
from stride_jax.jobs import closed_loop
from stride_jax.jobs.headline import check_entries
from stride_paper.report_control import slope_unseen
from stride_paper.seeds import (cell_at_most, fall_rates_differ, headline_picks, in_headline,
                                kind_and_seed, seed_means, welch)

KINDS = ("policy", "stride", "delan", "onn")


def _cell(rows: list[dict]) -> dict | None:
    """A kind's rows in one scenario: seeds' mean RMSE (over the seeds with an upright draw;
    NaN: none), falls of all episodes, mean ms per step of the episodes that ran alone (a
    vmapped part's ``--episodes N`` draws share each control step: their time is N episodes',
    not one planner's; all rows where none ran alone). A row that stayed up with no velocity
    RMSE (NaN: an episode run to time the controller, shorter than the settling time the error
    is scored after) carries no tracking and is left out; a cell of only such rows is None, not
    a loss (a NaN error that fell is one: no upright draw)."""
    rows = [r for r in rows if r.get("fell") or np.isfinite(r.get("vel_rmse", np.nan))]
    if not rows:
        return None
    means = seed_means(rows)
    alone = [r for r in rows if int(r.get("side_by_side") or 1) == 1] or rows
    timed = [r.get("controller_ms") for r in rows]
    return dict(vel_rmse=float(np.mean(list(means.values()))) if means else float("nan"),
                seed_means=[float(v) for v in means.values()],
                seeds=len({kind_and_seed(r)[1] for r in rows}), episodes=len(rows),
                falls=sum(bool(r["fell"]) for r in rows),
                ms_per_step=float(np.mean([r["ms_per_step"] for r in alone])),
                # the controller's own time per period (rows since session 80): where every row
                # has it, what the time target reads (one episode's, no simulated world)
                controller_ms=(float(np.mean(timed))
                               if all(t is not None for t in timed) else None))


# The tables' row order (the issue's: terrain, disturbances, commands); a variant (G1's tilt15,
# rough2) goes with its family, other names after these in the headline's order.
SCENARIO_ORDER = ("slope", "tilt", "rough", "push", "soft", "low_friction", "changes")


def _size(row: dict) -> tuple:
    """A planner row's samples and horizon, ``(K, H)`` (``(None, None)`` where not recorded)."""
    return row.get("K"), row.get("H")


def _sizes(rows: list[dict]) -> set[tuple]:
    """The recorded ``(K, H)`` of a kind's rows (empty where none recorded them)."""
    return {_size(r) for r in rows if r.get("H") is not None}


def _device(table: dict, row: dict):
    """The card a row ran on: its part's ``device`` (None where the table does not say)."""
    return (table.get("parts", {}).get(row.get("part")) or {}).get("device")


def _mean_time(rows: list[dict], key: str, sc: str) -> tuple[float | None, str]:
    """Mean ``key`` (``controller_ms`` or ``ms_per_step``) over the rows of scenario ``sc``, else
    over all of them, and which ("this scenario", "all scenarios"); None where there are none or
    one lacks it. ``ms_per_step`` reads the episodes that ran alone where any did (a vmapped
    part's draws share each step: ``_cell``)."""
    if key == "ms_per_step":
        rows = [r for r in rows if int(r.get("side_by_side") or 1) == 1] or rows
    pick = [r for r in rows if r["scenario"] == sc]
    frm = "this scenario" if pick else "all scenarios"
    vals = [r.get(key) for r in pick or rows]
    return (float(np.mean(vals)) if vals and all(v is not None for v in vals) else None), frm


def _time_cell(table: dict, sc: str, stride: list[dict], oracle: list[dict], timed: list[dict],
               sizes: set) -> dict:
    """The time target's cell of scenario ``sc``: STRIDE's time per step against the oracle's
    (rows at STRIDE's K and H), both read on one card (a part's ``device``: an H100 runs the
    oracle slower than an H200, which would flatter the ratio), the worst ratio over the cards
    both ran on. The sources in turn, the first that pairs on some card: the timing parts'
    controllers, the headline's controllers (``controller_ms``, no simulated world), the closed
    loop's steps. ``oracle_cards_apart``: the cards the oracle ran on where it shares none with
    STRIDE (the target then not measured there)."""
    sources = []
    if timed:  # the controllers timed apart, at the headline STRIDE's K and H
        at_size = [r for r in timed if not sizes or _size(r) in sizes]
        sources.append(("controller", "timing parts",
                        [r for r in at_size if kind_and_seed(r)[0] == "stride"],
                        [r for r in at_size if r["model"].split("@")[0] == "oracle"]))
    sources += [("controller", "headline", stride, oracle),
                ("closed-loop step", "headline", stride, oracle)]
    for basis, source, s_rows, o_rows in sources:
        key = "controller_ms" if basis == "controller" else "ms_per_step"
        pairs = {}
        for card in dict.fromkeys(_device(table, r) for r in s_rows):
            a, _ = _mean_time([r for r in s_rows if _device(table, r) == card], key, sc)
            b, frm = _mean_time([r for r in o_rows if _device(table, r) == card], key, sc)
            if a is not None and b:
                pairs[card] = (a, b, frm)
        if pairs:
            card, (a, b, frm) = max(pairs.items(), key=lambda kv: kv[1][0] / kv[1][1])
            ctl = basis == "controller"
            return dict(time_basis=basis, time_ratio=a / b, time_device=card, stride_time_ms=a,
                        oracle_time_ms=b, oracle_ms_from=frm,
                        controller_ms_from=source if ctl else None,
                        stride_controller_ms=a if ctl else None,
                        oracle_controller_ms=b if ctl else None,
                        oracle_ms=None if ctl else b, oracle_cards_apart=[])
    cards = sorted({str(_device(table, r)) for r in oracle})
    return dict(time_basis=None, time_ratio=None, time_device=None,
                stride_time_ms=_mean_time(stride, "ms_per_step", sc)[0], oracle_time_ms=None,
                oracle_ms=None, oracle_controller_ms=None, stride_controller_ms=None,
                controller_ms_from=None, oracle_ms_from=None, oracle_cards_apart=cards)


def _scenario_rank(scenario: str) -> int:
    family = scenario.rstrip("0123456789")
    return SCENARIO_ORDER.index(family) if family in SCENARIO_ORDER else len(SCENARIO_ORDER)


def robot_targets(table: dict, policy_pick: str = "", timing: tuple[str, ...] = ()) -> dict:
    """The scenarios' cells and the targets' verdicts of one merged table (``headline`` needed).
    ``timing``: parts run to time the controllers (``--controller-repeats``, one episode each):
    their STRIDE and oracle rows at the headline STRIDE's K and H give the controllers' own
    times (of the same scenario, else of all theirs), in place of the headline's, wherever they
    hold both."""
    picks = headline_picks(table)
    if not picks:
        raise ValueError("the table names no headline parts (stride_jax.jobs.closed_loop.merge "
                         "--headline): nothing says which rows are the current planner")
    rows = [r for r in table["rows"] if in_headline(r, picks)]
    scenarios = sorted(dict.fromkeys(r["scenario"] for r in rows), key=_scenario_rank)
    by: dict[tuple[str, str], list[dict]] = {(sc, k): [] for sc in scenarios for k in KINDS}
    for r in rows:
        kind = kind_and_seed(r)[0]
        if kind in KINDS:
            by[(r["scenario"], kind)].append(r)
    if policy_pick:
        model, _, parts = policy_pick.partition("@")
        picked = closed_loop.select(table["rows"], model, tuple(p for p in parts.split(",") if p))
        for sc in scenarios:
            by[(sc, "policy")] = [picked[sc]] if sc in picked else []
    every_oracle = [r for r in table["rows"] if r["model"].split("@")[0] == "oracle"]
    timed = [r for r in table["rows"] if r.get("part") in timing]
    for part in timing:
        if not any(r.get("part") == part for r in timed):
            raise ValueError(f"timing part {part!r}: no row of the table holds it")
    timed = [r for r in timed if r.get("controller_ms") is not None]
    if timing and not timed:
        raise ValueError(f"timing parts {', '.join(timing)}: no row with the controller's time "
                         "(run them with --controller-repeats)")
    cells = []
    for sc in scenarios:
        c = {k: _cell(by[(sc, k)]) for k in KINDS}
        # the oracle at STRIDE's samples and horizon (the "at the same K and H"): a
        # planner's time and tracking both follow them (session 88: G1's oracle at H 10 took
        # half its H 20 time); rows that record neither are taken as they are
        sizes = _sizes(by[(sc, "stride")])
        oracle = [r for r in every_oracle if not sizes or _size(r) in sizes]
        c["oracle_size"] = (", ".join(f"K {k}, H {h}" for k, h in sorted(sizes, key=str))
                            if sizes else None)
        c["oracle"] = _cell([r for r in oracle if r["scenario"] == sc and in_headline(r, picks)])
        s = c["stride"]
        c.update(_time_cell(table, sc, by[(sc, "stride")], oracle, timed, sizes))
        c["stride_vs"] = {k: cell_at_most(s, c[k]) for k in ("policy", "delan", "onn")}
        # the bar a right model sets: the same planner through the scenario's own MJX model
        # against the policy, and STRIDE against it (not targets; what they ask of the model)
        c["oracle_vs_policy"] = cell_at_most(c["oracle"], c["policy"])
        c["oracle_vs"] = {k: cell_at_most(c["oracle"], c[k]) for k in ("delan", "onn")}
        c["stride_vs_oracle"] = cell_at_most(s, c["oracle"])
        # a loss in error alone, over trained seeds on both sides: whether the seeds tell it apart
        c["apart"] = {k: (w["lo"] > 0) if (w := welch(s["seed_means"], c[k]["seed_means"])) else None
                      for k in ("policy", "delan", "onn")
                      if c["stride_vs"][k] is False
                      and not fall_rates_differ(s["falls"], s["episodes"], c[k]["falls"], c[k]["episodes"])}
        # a slope the controller could not sense (world-down gravity, runs before session 46)
        c["slope_unseen"] = any(slope_unseen(table, r) for k in KINDS for r in by[(sc, k)])
        cells.append(dict(scenario=sc, **c))
    runs = [c["stride"] for c in cells if c["stride"]]
    vs_policy = [c["stride_vs"]["policy"] for c in cells if c["stride_vs"]["policy"] is not None]
    base = [c["stride_vs"][k] for c in cells for k in ("delan", "onn")
            if c["stride_vs"][k] is not None]
    ratios = [c["time_ratio"] for c in cells if c["time_ratio"] is not None]
    # scenarios where STRIDE ran but no oracle at its K and H: the target is not measured there
    untimed = [c["scenario"] for c in cells if c["stride"] and c["time_ratio"] is None]
    # of those, the scenarios where an oracle ran at that size but on other cards than STRIDE
    apart = {c["scenario"]: c["oracle_cards_apart"] for c in cells
             if c["scenario"] in untimed and c["oracle_cards_apart"]}
    falls = sum(c[k]["falls"] for c in cells for k in ("stride", "delan", "onn") if c[k])
    episodes = sum(c[k]["episodes"] for c in cells for k in ("stride", "delan", "onn") if c[k])
    targets = {
        "no_falls": dict(met=sum(r["falls"] for r in runs) == 0 if runs else None,
                         stride_falls=sum(r["falls"] for r in runs),
                         stride_episodes=sum(r["episodes"] for r in runs),
                         all_models_falls=falls, all_models_episodes=episodes),
        "at_most_policy": dict(met=(sum(vs_policy) >= 0.75 * len(vs_policy)) if vs_policy else None,
                               scenarios=sum(vs_policy), of=len(vs_policy)),
        "at_most_baselines": dict(met=all(base) if base else None, comparisons=sum(base),
                                  of=len(base),
                                  # per baseline: the scenarios STRIDE is at most it in
                                  **{k: dict(scenarios=sum(bool(c["stride_vs"][k]) for c in cells),
                                             of=sum(c["stride_vs"][k] is not None for c in cells))
                                     for k in ("delan", "onn")}),
        "time_fifth_of_oracle": dict(met=(max(ratios) <= 0.2) if ratios and not untimed else None,
                                     worst_ratio=max(ratios) if ratios else None,
                                     no_oracle_at_stride_size=[sc for sc in untimed
                                                               if sc not in apart],
                                     oracle_on_other_cards=apart,
                                     cards=sorted({str(c["time_device"]) for c in cells
                                                   if c["time_ratio"] is not None})),
    }
    with_oracle = [c for c in cells if c["oracle_vs_policy"] is not None]
    reference = dict(  # not a target: what planning through the simulator itself reaches
        scenarios=[c["scenario"] for c in with_oracle],
        oracle_above_policy=[c["scenario"] for c in with_oracle if not c["oracle_vs_policy"]],
        stride_at_most_oracle=[c["scenario"] for c in cells if c["stride_vs_oracle"]],
        stride_vs_oracle_of=sum(c["stride_vs_oracle"] is not None for c in cells),
        # the baselines' target read for the oracle: whether a right model meets it either
        oracle_above_baseline=[f"{c['scenario']} ({k})" for c in cells for k in ("delan", "onn")
                               if c["oracle_vs"][k] is False],
        oracle_vs_baselines_of=sum(c["oracle_vs"][k] is not None for c in cells
                                   for k in ("delan", "onn")))
    return dict(headline=table["headline"]["parts"], timing=list(timing),
                policy=policy_pick or "the headline's own rows", cells=cells, targets=targets,
                oracle_reference=reference)


def _fmt(c: dict | None, digits: int = 3) -> str:
    if c is None:
        return "-"
    v = "n/a" if not np.isfinite(c["vel_rmse"]) else f"{c['vel_rmse']:.{digits}f}"
    return v + (f" ({c['falls']}/{c['episodes']} fell)" if c["falls"] else "")


def markdown(results: dict[str, dict], command: str) -> str:
    yes = {True: "**met**", False: "not met", None: "not measured"}
    lines = ["# Issue 19's closed-loop targets, per robot (the merged tables' headline parts)", "",
             f"Command: `{command}`", "",
             "Velocity RMSE (m/s): mean over trained seeds (each its planner draws that stayed up); "
             "falls over all episodes. STRIDE <= X: fewer falls, else the mean error at most X's; a loss "
             "in error alone says whether the trained seeds tell it apart (Welch's 90% interval of "
             "STRIDE minus X clear of 0; nothing said: one value on a side). Oracle: planning through "
             "the scenario's own MJX model at the same K and H, over the same policy (its headline rows; "
             "-: none run over this policy).", ""]
    for robot, res in results.items():
        t = res["targets"]
        lines += [f"## {robot}", "", f"Headline parts: {', '.join(res['headline'])}; policy rows: "
                  f"{res['policy']}.", "",
                  "| scenario | policy | STRIDE | DeLaN + MLP | ONN | oracle | STRIDE <= policy | <= DeLaN | "
                  "<= ONN | STRIDE ms/step | oracle ms/step | ratio | trained seeds / episodes: STRIDE, "
                  "DeLaN, ONN |",
                  "|---|---:|---:|---:|---:|---:|---|---|---|---:|---:|---:|---|"]
        for c in res["cells"]:
            vs = c["stride_vs"]
            apart = c["apart"]
            mark = lambda k: ("-" if vs[k] is None else "yes" if vs[k] else
                              "no" + {True: " (told apart)", False: " (not told apart)"}.get(apart.get(k), ""))
            ctl = c["time_basis"] == "controller"
            ms, orc_ms = c["stride_time_ms"], c["oracle_time_ms"]  # the ratio's, one card
            lines.append(
                f"| {c['scenario']}{' *' if c['slope_unseen'] else ''} | {_fmt(c['policy'])} | {_fmt(c['stride'])} | {_fmt(c['delan'])} | "
                f"{_fmt(c['onn'])} | {_fmt(c.get('oracle'))} | {mark('policy')} | {mark('delan')} | {mark('onn')} | "
                + (f"{ms:.1f}{' c' if ctl else ''}" if ms is not None else "-") + " | "
                + (f"{orc_ms:.0f}{' c' if ctl else ''}"
                   + (" (all scenarios)" if c["oracle_ms_from"] == "all scenarios" else "")
                   if orc_ms else "-") + " | "
                + (f"{c['time_ratio']:.2f}" if c["time_ratio"] is not None else "-") + " | "
                + ", ".join(f"{c[k]['seeds']}/{c[k]['episodes']}" if c[k] else "-"
                            for k in ("stride", "delan", "onn")) + " |")
        if any(c["time_basis"] == "controller" for c in res["cells"]):
            apart = any(c.get("controller_ms_from") == "timing parts" for c in res["cells"])
            lines += ["", "c: the controllers' own time per period (`controller_ms`: one episode's "
                          "planner and observer, no simulated world), where both rows have it"
                          + (f" (from the timing parts {', '.join(res['timing'])})"
                             if apart else "")
                          + "; other cells: the closed loop's ms per step"]
        if any(c["slope_unseen"] for c in res["cells"]):
            lines += ["", "\\* rows on a slope their controller could not sense (world-down gravity, runs "
                          "before session 46: `results/planning_diagnosis/README.md`)"]
        cell_size = {c["scenario"]: c.get("oracle_size") for c in res["cells"]}
        nf, ap, ab, tf = (t["no_falls"], t["at_most_policy"], t["at_most_baselines"],
                          t["time_fifth_of_oracle"])
        lines += ["", f"- no falls: {yes[nf['met']]} (STRIDE fell in {nf['stride_falls']} of "
                      f"{nf['stride_episodes']} episodes; all learned models {nf['all_models_falls']} of "
                      f"{nf['all_models_episodes']})",
                  f"- STRIDE at most the policy in at least 3 of 4 scenarios: {yes[ap['met']]} "
                  f"({ap['scenarios']} of {ap['of']})",
                  f"- at most DeLaN + MLP's and ONN's: {yes[ab['met']]} ({ab['comparisons']} of {ab['of']} "
                  "comparisons"
                  + "".join(f"; {name}'s in {ab[k]['scenarios']} of {ab[k]['of']} scenarios"
                            for k, name in (("delan", "DeLaN + MLP"), ("onn", "ONN"))
                            if ab.get(k, {}).get("of"))
                  + ")",
                  f"- at most 1/5 of the oracle's time per step: {yes[tf['met']]}"
                  + (f" (worst ratio {tf['worst_ratio']:.2f})" if tf["worst_ratio"] is not None else "")
                  + ("; no oracle row at STRIDE's K and H in " + ", ".join(
                      f"{sc} ({cell_size[sc]})" for sc in tf["no_oracle_at_stride_size"])
                     if tf.get("no_oracle_at_stride_size") else "")
                  + ("; the oracle at STRIDE's K and H only on other cards than STRIDE in "
                     + ", ".join(f"{sc} ({', '.join(cards)})"
                                 for sc, cards in tf["oracle_on_other_cards"].items())
                     if tf.get("oracle_on_other_cards") else "")
                  + (f"; each ratio's two times from one card ({', '.join(tf['cards'])})"
                     if tf.get("cards") and tf["cards"] != ["None"] else "")]
        ref = res.get("oracle_reference")
        if ref and ref["scenarios"]:
            n, above = len(ref["scenarios"]), ref["oracle_above_policy"]
            cell = {c["scenario"]: c for c in res["cells"]}
            lines.append(
                f"- for reference, not a target: the same planner through the scenario's own MJX "
                f"model (the oracle) at most the policy in {n - len(above)} of {n} scenarios"
                + (" (above it: " + ", ".join(f"{sc} {_fmt(cell[sc]['oracle'], 5)} against "
                                                f"{_fmt(cell[sc]['policy'], 5)}" for sc in above) + ")"
                   if above else "")
                + f"; STRIDE at most the oracle in {len(ref['stride_at_most_oracle'])} of "
                f"{ref['stride_vs_oracle_of']}"
                + (f" ({', '.join(ref['stride_at_most_oracle'])})" if ref["stride_at_most_oracle"] else "")
                + (f"; the oracle at most DeLaN + MLP's and ONN's in "
                   f"{ref['oracle_vs_baselines_of'] - len(ref['oracle_above_baseline'])} of "
                   f"{ref['oracle_vs_baselines_of']} comparisons"
                   + (f" (above: {', '.join(ref['oracle_above_baseline'])})"
                      if ref["oracle_above_baseline"] else "")
                   if ref.get("oracle_vs_baselines_of") else ""))
        lines.append("")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("tables", nargs="+", help="ROBOT=PATH of a merged closed_loop.json")
    ap.add_argument("--out", required=True, help="path stem: writes STEM.md and STEM.json")
    a, rest = ap.parse_known_args(argv)
    picks, heads, timings = {}, {}, {}
    it = iter(rest)
    for flag in it:  # --ROBOT-policy MODEL@PART,..., --ROBOT-headline ENTRY,..., --ROBOT-timing
        for suffix, into in (("-policy", picks), ("-headline", heads), ("-timing", timings)):
            if flag.startswith("--") and flag.endswith(suffix) and len(flag) > 2 + len(suffix):
                value = next(it, "")
                if not value or value.startswith("--"):
                    ap.error(f"{flag} needs a value")
                into[flag[2:-len(suffix)]] = value
                break
        else:
            ap.error(f"unknown argument {flag!r} (expected --ROBOT-policy MODEL@PART,..., "
                     "--ROBOT-headline ENTRY,... or --ROBOT-timing PART,...)")
    results = {}
    for spec in a.tables:
        robot, sep, path = spec.partition("=")
        if not sep or not robot or not path:
            ap.error(f"{spec!r}: expected ROBOT=PATH")
        p = pathlib.Path(path)
        if not p.is_file():
            ap.error(f"{p}: no such closed-loop table")
        table = json.loads(p.read_text())
        try:
            if robot in heads:  # another set of the table's rows read as its headline
                entries = [e for e in heads.pop(robot).split(",") if e]
                check_entries(entries, table.get("parts") or
                              sorted({r.get("part") for r in table["rows"]} - {None}),
                              table["rows"])
                table["headline"] = dict(parts=entries)
            timing = tuple(x for x in timings.pop(robot, "").split(",") if x)
            results[robot] = robot_targets(table, picks.pop(robot, ""), timing)
        except ValueError as e:
            ap.error(f"{p}: {e}")
    for flag, left in (("policy", picks), ("headline", heads), ("timing", timings)):
        if left:
            ap.error(f"--{'/'.join(left)}-{flag} names no table given")
    command = "python experiments/closed_loop_targets.py " + " ".join(
        argv if argv is not None else sys.argv[1:])
    stem = io.write_table(a.out, dict(command=command, robots=results), markdown(results, command))
    print(f"wrote {stem}.{{md,json}}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
