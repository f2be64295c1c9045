"""Scores of the independent gap benchmark: one row per diagnosis, the summary, the markdown table.

**Right or wrong** (:func:`score`). A verdict is right *strictly* when the effects it names are the
planted ones (in-library cases) or when it names none (the control, out-of-library effects). It is
right *as a set* when it is "explained" but not confident and its indistinguishable set
(:func:`stride_jax.gap.granularity.indistinguishable`) holds the planted effects: the logs cannot
tell the members apart (a servo gain error and a motor-constant error are the same dynamics
while nothing saturates) and the verdict says so, naming the set rather than a member.
``top1_single`` and ``top1_pairs`` count both; ``top1_single_strict`` only the first.
``ranked_first_single`` and ``ranked_first_pairs`` count, whatever the verdict, the diagnosis's best
hypothesis (its ranking's first row) being the planted effects (:func:`ranked_first`): the issue's
"the right effect ranked first", which a verdict of "unexplained by the library" can still have
where the calibrated simulator's leftover model-form difference outweighs the effect. A confident
call naming an effect that was not planted is a confident false attribution, set or not; so is one
naming only part of a pair whose every effect the logs show (``nameable``). A confident call naming
part of a pair that is not nameable (the named effect stands in for the other, which then adds
less than the materiality bar) is counted apart, as ``confident_partial``: it attributes the gap
to an effect that is there and misses one the logs cannot show.

**How far** (on the clean held-out trajectories, one-step gaps of :func:`stride_jax.gap.baseline.gap_of`):

* ``effect_shrink``: the part of the nominal model's gap that the *named* effects close on top of
  the tool's calibrated baseline (0 when the verdict names nothing: a user would add nothing);
* ``truth_shrink``: the same for the planted effects at their planted values, expressed as library
  parameters (:func:`truth_params`), on the same baseline: what the truth itself can close there;
* ``shrink_ratio`` = ``effect_shrink / truth_shrink``, whose median over the singles is
  ``median_shrink_single`` (issue 18: at least 80%). It is 1 when the named effect is the truth at
  its value; it is undefined where the truth closes nothing on top of the baseline;
* ``share_ratio`` = ``effect_shrink / effect_share``, with ``effect_share`` the gap that the "real"
  simulator settings without the effect leave (the definition before this round). It mixes in the
  model-form difference's cross term with the effect (``|m + e|^2 - |m|^2 = |e|^2 + 2 m.e``), so
  it reads 0.71 for torque_scale 0.65 fitted at 0.648; it is reported beside, not scored;
* ``nameable``: the truth closes at least the diagnosis's ``attribute_min`` (50%) of the
  baseline's gap. Where it does not, the calibrated simulator's leftover model-form difference
  outweighs the effect on these logs, and "unexplained by the library" is the honest verdict;
* ``truth_adds_last`` (pairs): what each planted effect closes of the baseline's gap when added
  last to the other at its planted value; below the diagnosis's ``pair_material`` (5%) the pair
  rule will not name it as a second effect;
* ``truth_adds_last_refit`` (pairs): the same, but against the other effect *re-fitted alone* on
  these trajectories rather than held at its planted value: what the logs show of each effect once
  the other may compensate for it (torque_scale 0.8 re-fitted at 0.75 stands in for most of a
  2 kg payload). A pair is ``nameable`` when it closes at least ``attribute_min`` and each effect
  adds at least ``pair_material`` in both senses; ``top1_pairs_nameable`` scores those only.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import mujoco
import numpy as np

from stride_jax.gap import baseline, diagnose, effects, fit
from stride_jax.jobs import gap_bench
from stride_jax.jobs.gap_bench import mean, med
from stride_jax.sim.model import SimModel


def truth_params(planted: dict[str, Any], base: SimModel) -> dict[str, np.ndarray] | None:
    """The planted effects as library parameters on ``base`` (the delay, planted in seconds, in
    simulation steps of ``base``), or None where one is not in the library."""
    out = {}
    for name, v in planted.items():
        if name == "delay":
            out[name] = np.array([round(float(np.ravel(v)[0]) / base.mj.opt.timestep)], float)
        elif name in effects.ALL and effects.ALL[name].in_library and effects.ALL[name].applies(base):
            out[name] = np.atleast_1d(np.asarray(v, float))
        else:
            return None
    return out


def _form_model(sm: SimModel, form: mujoco.MjModel) -> SimModel:
    """The "real" simulator without the planted effects, as a model the tool can replay."""
    return dataclasses.replace(sm, mj=form, n_substeps=int(round(sm.robot.ctrl_dt / form.opt.timestep)))


def in_set(verdict: dict, planted: set) -> bool:
    """Whether a verdict's indistinguishable set holds a member that is the planted effects."""
    s = verdict.get("indistinguishable_set") or {}
    return any(set(m.split("+")) == planted for m in s.get("effects", []))


def score(sm: SimModel, case: dict, res: dict, clean_held: list, settings: dict, form: mujoco.MjModel,
          attribute_min: float = 0.5, pair_material: float = 0.05, fit_cfg: fit.FitConfig | None = None
          ) -> dict[str, Any]:
    """One row: the verdict against the planted truth, the calibration against the drawn
    settings, and shrinks on the clean held-out trajectories."""
    v = res["verdict"]
    planted = set(case["planted"])
    explained = v["verdict"] == "explained"
    named = set(v["effects"]) if explained else set()
    in_lib = case["kind"] in ("single", "pair")
    cal = res.get("calibration") or {}
    sets = v.get("indistinguishable_set") or {}
    row: dict[str, Any] = {
        "kind": case["kind"], "planted": {k: np.atleast_1d(x).tolist() for k, x in case["planted"].items()},
        "real_settings": settings, "verdict": v["verdict"], "named": sorted(named), "confident": bool(v["confident"]),
        "ties": v.get("indistinguishable_from", []), "indistinguishable_set": sets.get("effects", []),
        "calibration": cal.get("changed", []), "calibration_settings": cal.get("settings"), "reason": v["reason"],
        "seconds": res["seconds"]}
    row["correct_strict"] = (named == planted) if in_lib else (not named)
    row["correct_as_set"] = bool(in_lib and explained and not v["confident"] and named != planted
                                 and in_set(v, planted))
    row["correct"] = row["correct_strict"] or row["correct_as_set"]
    row["confident_false"], row["confident_partial"] = confident_false(row)  # again once "nameable" is known
    wh = res.get("which")
    if not wh:
        return row
    det = wh["detection"]
    row["detection"] = {"p_value": det["p_value"], "level": det["level"], "significant": bool(det["significant"]),
                        "probe_explained": wh["probe_explained_nominal"], "rule": v.get("rule")}
    best = wh["ranking"][0]
    row["best"] = {"effects": best["effects"], "params": best["params"], "lo": best["param_lo"],
                   "hi": best["param_hi"], "explained": best["explained"]}
    hf = res["how_far"]
    row["tool"] = {k: hf.get(k) for k in ("gap_nominal", "gap_baseline", "gap_final", "shrink_vs_nominal",
                                           "shrink_vs_baseline", "calibration_shrink")}
    data1 = list(clean_held)
    held = fit.make_data(data1)
    scale = diagnose.scale_of(sm, held)
    base = baseline.baseline_of(sm, cal)
    g_nom = baseline.gap_of(sm, data1, scale)
    g_base = baseline.gap_of(base, data1, scale)
    g_final = baseline.gap_of(base, data1, scale, applied=best["params"] if explained else None)
    g_form = baseline.gap_of(_form_model(sm, form), data1, scale)
    tiny = 1e-300
    c = {"gap_nominal": g_nom, "gap_baseline": g_base, "gap_final": g_final, "gap_true_form": g_form,
         "shrink_vs_nominal": 1 - g_final / max(g_nom, tiny), "shrink_vs_baseline": 1 - g_final / max(g_base, tiny),
         "calibration_shrink": 1 - g_base / max(g_nom, tiny), "effect_share": g_form / max(g_nom, tiny),
         "effect_shrink": (g_base - g_final) / max(g_nom, tiny)}
    truth = truth_params(case["planted"], base) if in_lib else None
    if truth is not None:
        g_truth = baseline.gap_of(base, data1, scale, applied=truth)
        c |= {"gap_truth": g_truth, "truth_shrink": (g_base - g_truth) / max(g_nom, tiny),
              "truth_closes": 1 - g_truth / max(g_base, tiny), "truth_params": {k: x.tolist() for k, x in truth.items()}}
        row["nameable"] = bool(c["truth_closes"] >= attribute_min)
        if len(truth) > 1:  # what each planted effect adds last, as a share of the baseline's gap
            c["truth_adds_last"] = {
                n: (baseline.gap_of(base, data1, scale, applied={k: x for k, x in truth.items() if k != n}) - g_truth)
                / max(g_base, tiny) for n in truth}
            fcfg = dataclasses.replace(fit_cfg or fit.FitConfig(), profile=0, refits=0)
            c["truth_adds_last_refit"] = {}
            for n in truth:
                rest = tuple(k for k in truth if k != n)
                alone = fit.fit(base, held, scale, rest, fcfg, {k: truth[k] for k in rest})
                c["truth_adds_last_refit"][n] = ((baseline.gap_of(base, data1, scale, applied=alone.params) - g_truth)
                                                 / max(g_base, tiny))
            adds = list(c["truth_adds_last"].values()) + list(c["truth_adds_last_refit"].values())
            row["nameable"] = bool(row["nameable"] and min(adds) >= pair_material)
        if c["truth_shrink"] > 0:
            row["shrink_ratio"] = c["effect_shrink"] / c["truth_shrink"]
        row["share_ratio"] = c["effect_shrink"] / max(c["effect_share"], tiny)
    row["clean"] = c
    row["confident_false"], row["confident_partial"] = confident_false(row)
    return row


def ranked_first(row: dict) -> bool:
    """Whether the diagnosis ranked the planted effects first (its best hypothesis, verdict aside);
    False where it ranked nothing (no significant gap)."""
    best = (row.get("best") or {}).get("effects")
    return bool(best) and set(best) == set(row["planted"])


def confident_false(row: dict) -> tuple[bool, bool]:
    """``(confident false attribution, confident partial)`` for a scored row (module docstring)."""
    named, planted = set(row["named"]), set(row["planted"])
    if not (row["confident"] and named):
        return False, False
    if row["kind"] not in ("single", "pair") or named - planted:
        return True, False
    if named == planted:
        return False, False
    partial = row["kind"] == "pair" and row.get("nameable") is False
    return not partial, partial


def summary(rows: list[dict]) -> dict[str, Any]:
    out = {}
    for label, rs, kind in gap_bench.by_noise(rows):
        singles, pairs, ctrl = kind["single"], kind["pair"], kind["control"]
        nameable = [r for r in singles if r.get("nameable")]
        pairs_nameable = [r for r in pairs if r.get("nameable")]
        out[label] = {
            "top1_single": mean([r["correct"] for r in singles]),
            "top1_pairs": mean([r["correct"] for r in pairs]),
            "median_shrink_single": med([r["shrink_ratio"] for r in singles if "shrink_ratio" in r]),
            "confident_false": int(sum(confident_false(r)[0] for r in rs)),
            "confident_partial": int(sum(confident_false(r)[1] for r in rs)),
            "control_verdict": [f"{r['verdict']}" + (f" (sign-flip p = {r['detection']['p_value']:.3g})"
                                                     if "detection" in r else "")
                                + f"; simulator settings found: {'; '.join(r['calibration']) or 'none'} "
                                f"(drawn: {r['real_settings']})" for r in ctrl],
            "top1_single_strict": mean([r["correct_strict"] for r in singles]),
            "ranked_first_single": mean([ranked_first(r) for r in singles]),
            "ranked_first_pairs": mean([ranked_first(r) for r in pairs]),
            "right_as_set": sorted("+".join(r["planted"]) for r in rs if r["correct_as_set"]),
            "not_nameable": sorted("+".join(r["planted"]) for r in singles if r.get("nameable") is False),
            "top1_single_nameable": mean([r["correct"] for r in nameable]),
            "pairs_not_nameable": sorted("+".join(r["planted"]) for r in pairs if r.get("nameable") is False),
            "top1_pairs_nameable": mean([r["correct"] for r in pairs_nameable]),
            "median_share_ratio_single": med([r["share_ratio"] for r in singles if "share_ratio" in r]),
            "median_shrink_vs_nominal_single": med([r["clean"]["shrink_vs_nominal"] for r in singles if "clean" in r]),
            "median_calibration_shrink": med([r["clean"]["calibration_shrink"] for r in rs if "clean" in r]),
            "out_of_library_verdicts": [r["verdict"] for r in kind["out_of_library"]],
            # no-effect cases: on how many a gap was left on top of the calibrated settings (detected:
            # the calibration did not take up all of the simulator's form), and on how many a physical
            # effect was named for it (a false attribution, confident or not)
            "controls_detected": int(sum(r["verdict"] != "no significant gap" for r in ctrl)),
            "controls_named": int(sum(r["verdict"] == "explained" for r in ctrl)),
            "controls": len(ctrl),
            "cases": len(rs),
        }
    return out


def markdown(cfg, rows: list[dict], summ: dict, command: str, seconds: float) -> str:
    f = lambda x: "-" if x is None else (f"{x:.3g}" if isinstance(x, float) else str(x))
    L = [f"# Sim-to-real gap: independent benchmark ({cfg.robot})", "", f"Command: `{command}`", "",
         f"{cfg.trajectories} trajectories x {cfg.steps} control steps per case, written by independent code "
         f"(`stride_jax/jobs/gap_bench_real.py`) with simulator settings drawn per case; diagnosis preset "
         f"`{cfg.diagnose}` on the shipped nominal model; {len(rows)} diagnoses, {seconds / 60:.1f} min of "
         "compute summed over them. Scoring: `stride_jax/jobs/gap_bench_score.py` (its docstring defines every "
         "column).", "",
         "Targets (issue 18): top-1 >= 90% on single effects, pairs named right >= 80%, held-out shrink >= 80% "
         "of the planted effect's share on clean logs (`median_shrink_single`: what the named effect closes on top "
         "of the calibrated baseline over what the planted effect at its planted value closes there), no "
         "confident false attribution, the control says what the model-form difference is.", "",
         "A verdict counts as right when it names the planted effects, or when it is not confident and names an "
         "indistinguishable set that holds them (`right_as_set`); `top1_single_strict` counts the first only. "
         "`ranked_first_single` / `ranked_first_pairs`: the diagnosis's best hypothesis is the planted effects, "
         "whatever the verdict (\"the right effect ranked first\"; an \"unexplained\" verdict can still rank it "
         "first). "
         "`not_nameable`: singles whose planted effect, at its planted value, closes less than 50% of the "
         "calibrated baseline's gap (the rule for naming an effect): the model-form difference outweighs it. "
         "`pairs_not_nameable`: pairs of which one effect, added last at its planted value, closes less than the "
         "5% of the baseline's gap that the pair rule asks of a second effect by its share (the diagnosis still "
         "names such a second effect, not confidently, where leaving it out moves the first one's value by 10% "
         "or more: a confounder).",
         "", "| metric | noise-free | noisy |", "|---|---|---|"]
    for k in ("top1_single", "top1_pairs", "median_shrink_single", "confident_false", "confident_partial",
              "top1_single_strict", "ranked_first_single", "ranked_first_pairs",
              "right_as_set", "not_nameable", "top1_single_nameable", "pairs_not_nameable",
              "top1_pairs_nameable", "median_share_ratio_single",
              "median_shrink_vs_nominal_single", "median_calibration_shrink", "out_of_library_verdicts",
              "controls_detected", "controls_named", "controls"):
        L.append(f"| {k} | {f(summ.get('noise_free', {}).get(k))} | {f(summ.get('noisy', {}).get(k))} |")
    L += ["", "Control:", ""]
    for key in ("noise_free", "noisy"):
        for line in summ.get(key, {}).get("control_verdict", []):
            L.append(f"- {key}: {line}")
    L += ["", "| noise | kind | planted | verdict | named | confident | right | set | best fit | truth closes "
          "(of baseline gap) | effect shrink | truth shrink | ratio | calibration found |",
          "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        c = r.get("clean", {})
        right = "strict" if r["correct_strict"] else ("as set" if r["correct_as_set"] else "no")
        L.append(f"| {'noisy' if r['noisy'] else 'clean'} | {r['kind']} | {r['planted']} | {r['verdict']} | "
                 f"{'+'.join(r['named']) or '-'} | {r['confident']} | {right} | "
                 f"{', '.join(r.get('indistinguishable_set', [])) or '-'} | {r.get('best', {}).get('params', '-')} | "
                 f"{f(c.get('truth_closes'))} | {f(c.get('effect_shrink'))} | {f(c.get('truth_shrink'))} | "
                 f"{f(r.get('shrink_ratio'))} | {'; '.join(r['calibration']) or '-'} |")
    L += ["", "Drawn \"real\" simulator settings per case:", ""]
    for r in rows:
        if not r["noisy"]:
            last = r.get("clean", {}).get("truth_adds_last")
            refit = r.get("clean", {}).get("truth_adds_last_refit")
            L.append(f"- case {r['case']} ({r['kind']}, {r['planted']}): {r['real_settings']}"
                     + (f"; each planted effect added last closes {({k: round(x, 4) for k, x in last.items()})} "
                        "of the baseline's gap" if last else "")
                     + (f", and {({k: round(x, 4) for k, x in refit.items()})} against the other re-fitted alone"
                        if refit else ""))
    return "\n".join(L) + "\n"
