"""``stride gap diagnose``'s output: a diagnosis as ``report.md`` with plots (matplotlib, Agg) and
``diagnosis.json``."""

from __future__ import annotations

import json
import os
import pathlib
from typing import Any

import numpy as np

from stride_jax import io


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: pathlib.Path) -> str:
    io.atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=90, bbox_inches="tight"))
    _plt().close(fig)
    return path.name


def plots(d: dict[str, Any], out: pathlib.Path) -> dict[str, str]:
    """Residual per dof, residual against joint velocity, over time, rollout divergence, ranking."""
    plt = _plt()
    w, files = d["where"], {}
    names = list(w["per_dof_rms_scaled"])
    fig, ax = plt.subplots(figsize=(max(5, 0.35 * len(names)), 3))
    ax.bar(range(len(names)), list(w["per_dof_rms_scaled"].values()))
    ax.set_xticks(range(len(names)), names, rotation=90, fontsize=7)
    ax.set_ylabel("one-step residual RMS (scaled)")
    ax.set_title("Where: nominal residual per dof")
    files["per_dof"] = _save(fig, out / "residual_per_dof.png")

    jv = w["joint_velocity_bins"]
    fig, ax = plt.subplots(figsize=(6, 3.5))
    for j, bins in jv.items():
        c = [b["centre"] for b in bins if b["mean"] is not None]
        m = [b["mean"] for b in bins if b["mean"] is not None]
        ax.plot(c, m, marker=".", lw=1, label=j)
    ax.axhline(0, color="k", lw=0.5)
    ax.set_xlabel("joint velocity (rad/s)")
    ax.set_ylabel("mean residual (rad/s^2)")
    ax.set_title("Residual against the joint's own velocity")
    if len(jv) <= 12:
        ax.legend(fontsize=6, ncol=2)
    files["velocity"] = _save(fig, out / "residual_vs_velocity.png")

    fig, ax = plt.subplots(figsize=(5, 3))
    ot = [b for b in w["over_time"] if b["rms"] is not None]
    ax.plot([(b["t0_s"] + b["t1_s"]) / 2 for b in ot], [b["rms"] for b in ot], marker="o")
    ax.set_xlabel("time in trajectory (s)")
    ax.set_ylabel("residual RMS (scaled)")
    ax.set_title("Over time")
    files["time"] = _save(fig, out / "residual_over_time.png")

    hf = d.get("how_far")
    if hf and hf["rollout_before"]["rmse"] is not None:
        fig, axs = plt.subplots(1, 2, figsize=(10, 3.2), sharey=True)
        for ax, key, title in ((axs[0], "rollout_before", "nominal"), (axs[1], "rollout_after", "with identified effect")):
            div = hf[key]
            e = np.asarray(div["rmse"])
            for i, n in enumerate(div["names"]):
                ax.plot(np.arange(1, len(e) + 1), e[:, i], lw=1, label=n)
            ax.set_xlabel("control steps")
            ax.set_title(f"Open-loop divergence: {title}")
            ax.set_yscale("log")
        axs[0].set_ylabel("RMSE (rad or m)")
        if len(hf["rollout_before"]["names"]) <= 16:
            axs[1].legend(fontsize=6, ncol=2)
        files["divergence"] = _save(fig, out / "divergence.png")

    wh = d.get("which")
    if wh:
        rows = wh["ranking"][:12]
        fig, ax = plt.subplots(figsize=(6, 0.3 * len(rows) + 1.2))
        lab = ["+".join(r["effects"]) for r in rows][::-1]
        x = [r["explained"] for r in rows][::-1]
        lo = [r["explained"] - r["explained_ci"][0] for r in rows][::-1]
        hi = [r["explained_ci"][1] - r["explained"] for r in rows][::-1]
        ax.barh(range(len(rows)), x, xerr=[np.maximum(lo, 0), np.maximum(hi, 0)])
        ax.set_yticks(range(len(rows)), lab, fontsize=7)
        ax.set_xlabel("held-out gap explained (90% bootstrap CI)")
        ax.set_title("Which: candidate effects")
        files["ranking"] = _save(fig, out / "ranking.png")
    if d.get("residual"):
        files["residual"] = _save(residual_figure(d["residual"]), out / "residual_concentration.png")
    return files


def residual_figure(res: dict[str, Any]):
    """Where the STRIDE residual on top of the best hypothesis concentrates: fitted against left
    per dof, and the signed mean per bin of each joint's velocity and position (solid: fitted,
    dashed: left), plus contact phases when the robot has feet."""
    plt = _plt()
    c = res["concentration"]
    feet = c["per_foot_phase"]
    fig, axs = plt.subplots(1, 4 if feet else 3, figsize=(15 if feet else 12, 3.4))
    names = list(c["per_dof"])
    x = np.arange(len(names))
    axs[0].bar(x - 0.2, [c["per_dof"][n]["rms_scaled"] for n in names], 0.4, label="fitted")
    axs[0].bar(x + 0.2, [c["per_dof"][n]["left_rms_scaled"] for n in names], 0.4, label="left")
    axs[0].set_xticks(x, names, rotation=90, fontsize=7)
    axs[0].set_ylabel("RMS (scaled)")
    axs[0].set_title("Per dof")
    axs[0].legend(fontsize=7)
    for ax, key, label in ((axs[1], "joint_velocity_bins", "joint velocity (rad/s)"),
                           (axs[2], "joint_position_bins", "joint position from home (rad)")):
        for i, (j, bins) in enumerate(c[key].items()):
            rows = [b for b in bins if b["count"]]
            col = f"C{i % 10}"
            ax.plot([b["centre"] for b in rows], [b["mean"] for b in rows], marker=".", lw=1, color=col, label=j)
            ax.plot([b["centre"] for b in rows], [b["left_mean"] for b in rows], ls="--", lw=0.8, color=col)
        ax.axhline(0, color="k", lw=0.5)
        ax.set_xlabel(label)
        ax.set_title("Mean per bin (solid fitted, dashed left)", fontsize=9)
    axs[1].set_ylabel("acceleration (rad/s² or m/s²)")
    if len(c["joint_velocity_bins"]) <= 12:
        axs[1].legend(fontsize=6, ncol=2)
    if feet:
        phases = ("swing", "stance", "touchdown", "liftoff")
        width = 0.8 / len(phases)
        for k, ph in enumerate(phases):
            axs[3].bar(np.arange(len(feet)) + (k - 1.5) * width,
                       [rows[ph]["rms"] or 0.0 for rows in feet.values()], width, label=ph)
        axs[3].set_xticks(range(len(feet)), list(feet))
        axs[3].set_ylabel("fitted RMS (scaled)")
        axs[3].set_title("Per foot and contact phase")
        axs[3].legend(fontsize=7)
    fig.suptitle(f"STRIDE residual on top of the best: explains {res['explained']:.1%} of the held-out gap left")
    fig.tight_layout()
    return fig


def _fmt(v, p=4):
    if v is None:
        return "-"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_fmt(x, p) for x in v) + "]"
    return f"{v:.{p}g}" if isinstance(v, float) else str(v)


def markdown(d: dict[str, Any], files: dict[str, str], command: str | None = None) -> str:
    v = d["verdict"]
    L = [f"# Sim-to-real gap diagnosis: {d['robot']}", ""]
    if command:
        L += [f"Command: `{command}`", ""]
    L += [f"**Verdict: {v['verdict']}**" + (f" — {' + '.join(v['effects'])}" if v["effects"] else "")
          + (" (confident)" if v.get("confident") and v["effects"] else ""), "", v["reason"], "",
          f"{d['n_trajectories']} trajectories ({len(d['train'])} train, {len(d['heldout'])} held out), "
          f"{d['n_samples']} one-step replays; {d['preprocess']['outliers_replaced']} velocity outliers "
          f"replaced; smoothing bandwidth: {_fmt(d['preprocess']['smoothing_bandwidth_hz'])} Hz "
          f"(None = no smoothing). Took {d['seconds']:.1f} s.", "",
          f"Residual: {d['residual_definition']}.", ""]
    L += calibration_section(d)
    w = d["where"]
    L += ["## Where", "", f"![per dof]({files.get('per_dof')})", "",
          "| dof | RMS (rad/s² or m/s²) | scaled |", "|---|---|---|"]
    for n in w["per_dof_rms"]:
        L.append(f"| {n} | {w['per_dof_rms'][n]:.4g} | {w['per_dof_rms_scaled'][n]:.3g} |")
    if w["per_foot_phase"]:
        L += ["", "Contact phase per foot (from foot heights; scaled RMS over all dofs / the leg's joints):", "",
              "| foot | swing | stance | touchdown | liftoff |", "|---|---|---|---|---|"]
        for foot, rows in w["per_foot_phase"].items():
            cells = [f"{_fmt(rows[p]['rms_all'], 3)} / {_fmt(rows[p]['rms_leg'], 3)} (n={rows[p]['count']})"
                     for p in ("swing", "stance", "touchdown", "liftoff")]
            L.append(f"| {foot} | " + " | ".join(cells) + " |")
    if "base_speed_bins" in w:
        L += ["", "| base speed (m/s) | n | RMS (scaled) |", "|---|---|---|"]
        L += [f"| {b['lo']:.2f}-{b['hi']:.2f} | {b['count']} | {b['rms']:.3g} |" for b in w["base_speed_bins"]]
    L += ["", f"![velocity]({files.get('velocity')}) ![time]({files.get('time')})", ""]
    wh = d.get("which")
    if wh:
        L += ["## Which", "", f"![ranking]({files.get('ranking')})", "",
              f"Nominal held-out gap (mean squared scaled {d['config']['steps']}-step residual): {wh['gap_ms']:.4g}; "
              f"noise floor estimate {wh['noise_floor']:.4g}; linear probe on the nominal residual explains "
              f"{wh['probe_explained_nominal']:.1%}; systematic structure left after the best: {wh['structure_left']:.1%}.", "",
              f"| rank | effects | parameters | {d['config'].get('fit', {}).get('level', 0.9):.0%} interval | held-out explained | 90% CI | above floor | score | P(beats next) |",
              "|---|---|---|---|---|---|---|---|---|"]
        for i, r in enumerate(wh["ranking"]):
            flag = " (at the bound)" if any(any(v) for v in r.get("at_bound", {}).values()) else ""
            iv = (f"{_fmt(r['param_lo'])} – {_fmt(r['param_hi'])}" if r.get("interval", True)
                  else "not computed (not named)")
            L.append(f"| {i + 1} | {'+'.join(r['effects'])} | {_fmt(r['params'])}{flag} | {iv} | "
                     f"{r['explained']:.1%} | [{r['explained_ci'][0]:.1%}, "
                     f"{r['explained_ci'][1]:.1%}] | {r['explained_above_floor']:.1%} | {r['score']:.3f} | "
                     f"{r['p_beats_next']:.2f} |")
        level = d["config"].get("fit", {}).get("level", 0.9)
        L += ["", f"Parameter intervals: {level:.0%} profile-likelihood (scalars) or sandwich (vectors, pairs) intervals of the "
              "training loss, calibrated by the spread of its gradient over blocks of the logs, clipped to the "
              "parameter's bounds; they contain the estimate. They cover sampling noise only, not the bias that "
              "sensor noise in the replayed start states gives the estimate, and they are conditional on the "
              "simulator's settings above: the model-form difference those leave biases the estimate the same way on "
              "every trajectory, beyond the interval (on logs from independently set-up simulators most intervals "
              "missed the planted value; docs/gap.md, \"Still short of the issue\"). \"(at the bound)\": the "
              "estimate sits on a bound of its parameter: the true value may lie beyond it. Single effects "
              "other than the two best held out and the named one are fitted without an interval (a third of a fit's "
              "replays)."]
        det = wh.get("detection") or {}
        if det:
            L += ["", f"Detection (cross-fitted, {det['blocks']} blocks): sign-flip p = {det['p_value']:.3g} (Monte Carlo "
                  f"floor {det.get('p_floor', 0):.2g}, normal approximation {det.get('p_normal', float('nan')):.2g}), "
                  f"level {det['level']:.3g}."]
        u = wh.get("unstable") or {}
        if u.get("diverged_replays"):
            L += ["", f"Unstable simulation: {u['diverged_replays']} replays diverged (NaN/Inf; MuJoCo warned "
                  f"{u['mujoco_warnings']} times, not printed) in {u['fits']} fit evaluations and {u['pair_screen']} of "
                  "the pair screen; those parameter values scored as very bad fits."]
        fc = wh.get("form_check")
        if fc:
            one = lambda v: _fmt(v[0] if len(v) == 1 else v)
            iv = lambda h: f" [{one(fc[h + '_lo'])}, {one(fc[h + '_hi'])}]" if fc.get(h + "_lo") is not None else ""
            L += ["", f"Form check ({fc['effect']} refitted where each joint moves slowest and where it moves fastest, "
                  f"the {fc['share']:.0%} of its samples below and above median cuts of {fc['cuts'][0]:.2f} and "
                  f"{fc['cuts'][1]:.2f} rad/s): {one(fc['slow'])}{iv('slow')} against {one(fc['fast'])}{iv('fast')}: "
                  + ("they **differ** (beyond both intervals and by more than "
                     f"{fc['tol']:.0%}): an effect of this form does not fit both" if fc["differs"] else "they agree")
                  + ("" if fc.get("slow_lo") is not None else
                     f" (within {fc['tol']:.0%} of each other, so their intervals were not needed)")
                  + "."]
        ties = d["verdict"].get("indistinguishable_from") or []
        L += ["", "Indistinguishable from the best on these logs: " + (", ".join(ties) if ties else "none") + "."]
        L += screen_lines(d)
        L += ["", "Nominal check (max |residual change| of each candidate at its nominal value): "
              + ", ".join(f"{k} {v:.1g}" for k, v in d["nominal_check"].items()), ""]
    hf = d.get("how_far")
    if hf:
        L += ["## How far (held-out)", "",
              f"One-step gap (mean squared scaled residual): {hf['gap_before']:.4g} → {hf['gap_after']:.4g} "
              f"(shrink {hf['shrink']:.1%}); {d['config']['steps']}-step: {hf['kstep_gap_before']:.4g} → "
              f"{hf['kstep_gap_after']:.4g} (shrink {hf['kstep_shrink']:.1%}).",
              f"{d['config']['horizon']}-step open-loop rollout, mean final RMSE over dofs: "
              f"{_fmt(hf['rollout_final_rmse_mean_before'])} → {_fmt(hf['rollout_final_rmse_mean_after'])}.", "",
              "| dof | one-step acc RMSE before | after |", "|---|---|---|"]
        for n in hf["one_step_acc_rmse_before"]:
            L.append(f"| {n} | {hf['one_step_acc_rmse_before'][n]:.4g} | {hf['one_step_acc_rmse_after'][n]:.4g} |")
        if "gap_nominal" in hf:
            L += ["", f"Against the nominal model and the calibrated baseline (held-out one-step gap): nominal "
                  f"{hf['gap_nominal']:.4g} → baseline {hf['gap_baseline']:.4g} (the settings alone: shrink "
                  f"{hf['calibration_shrink']:.1%}) → with the effect {hf['gap_final']:.4g}: **shrink "
                  f"{hf['shrink_vs_nominal']:.1%} against the nominal model, {hf['shrink_vs_baseline']:.1%} against the "
                  f"calibrated baseline**."]
        if "divergence" in files:
            L += ["", f"![divergence]({files['divergence']})"]
        L += ["", "Per-foot force error: not available (the logs carry no contact forces)."]
    L += residual_section(d, files)
    return "\n".join(L)


def screen_lines(d: dict[str, Any]) -> list[str]:
    """The indistinguishable set with its reasons, and the screen's top candidates."""
    L = []
    st = d["verdict"].get("indistinguishable_set")
    if st:
        L += ["", "Indistinguishable set: " + ", ".join(st["effects"]) + "."]
        L += [f"- {k}: {v}" for k, v in st["reasons"].items()]
    scr = d.get("screen")
    if scr:
        L += ["", f"Screen ({scr['candidates']} candidates, {scr['parameters']} parameters, {scr['windows'][0]} + "
              f"{scr['windows'][1]} windows, {scr['seconds']:.0f} s): fitted in full: {', '.join(scr['shortlist'])}.", "",
              "| candidate | linearised, cross-validated explained | held out at the linear estimate |", "|---|---|---|"]
        for r in scr["table"][:10]:
            chk = r.get("checked_heldout")
            L.append(f"| {r['effect']} | {r.get('linear_cv', r.get('linear_heldout', float('nan'))):.1%} | {'' if chk is None else f'{chk:.1%}'} |")
    return L


def _refine_groups(r: dict[str, Any]) -> list[str]:
    """What the refinement's screen said of the joint groups it took (``CalibrateConfig.refine_finer``)."""
    rows = (r.get("screen") or {}).get("screen") or []
    skip = (r.get("screen") or {}).get("group_not_held")
    held = next(iter(r.get("held_fixed") or {}), None)
    lib = next((x for x in rows if "@" not in x["effect"]), None)
    if skip:
        return ["", f"The joint group {skip['group']} came within {skip['margin']:.0%} of {skip['library']}'s training "
                    f"loss ({skip['loss']:.4g} against {skip['library_loss']:.4g}): the library effect was held."]
    if held and "@" in held and lib and lib["loss"] > 0:
        mine = next(x["loss"] for x in rows if x["effect"] == held)
        return ["", f"{held} is a joint group: its training loss was {mine / lib['loss']:.1%} of the best library "
                    f"effect's ({lib['effect']})."]
    return []


def calibration_section(d: dict[str, Any]) -> list[str]:
    """The simulator's settings, calibrated before the effects (:mod:`stride_jax.gap.calibrate`):
    what the nominal model uses, what the logs call for, and how much of the gap that closes."""
    c = d.get("calibration")
    L = ["## Model form: the simulator's settings (calibrated first)", ""]
    if not c or c.get("mode") == "off":
        return L + ["Not calibrated (`calibrate.mode = off`, or the nominal model replays the logs exactly): the "
                    "effects are scored against the nominal model.", ""]
    ns = c["nominal_settings"]
    L += [f"Nominal model: time step {ns['timestep'] * 1e3:g} ms, integrator {ns['integrator']}, {ns['cone']} cone, "
          f"impratio {ns['impratio']:g}, contacts: {ns['contacts']} ({ns['colliding_geoms']} colliding geoms"
          + (f", foot condim {ns['foot_condim']}" if ns.get("foot_condim") else "") + f"), solref {ns['solref']}, "
          f"solimp {ns['solimp']}, margin {ns['margin']}.", ""]
    if c["applied"]:
        L += ["**The simulator's settings differ from the nominal model:**", ""]
        L += [f"- {line}" for line in c["changed"]]
        L += ["", f"Held-out {c['k']}-step gap: nominal {c['heldout_gap_nominal']:.4g} → calibrated "
              f"{c['heldout_gap_calibrated']:.4g} (shrink {c['shrink']:.1%}; one-sided sign-flip p = {c['p_value']:.2g} "
              "over held-out blocks). The physical effects below are fitted and scored on top of this baseline."]
    else:
        L += ["The settings stay as the nominal model has them: "
              + (f"the proposal ({'; '.join(c['proposed'])}) did not lower the held-out gap "
                 f"({c['heldout_gap_nominal']:.4g} → {c['heldout_gap_proposed']:.4g})." if c["proposed"]
                 else "no setting lowered the training loss by the required margin.")]
    ties = c.get("discrete_ties") or {}
    if ties:
        L += ["", "Indistinguishable on these logs (within the margin of the chosen value): "
              + "; ".join(f"{k}: {v}" for k, v in ties.items()) + "."]
    forms = c.get("forms_heldout") or {}
    if len(forms) > 1:
        L += ["", "Model-form hypotheses, held-out gap without any effect: "
              + ", ".join(f"{k} {v:.4g}" for k, v in forms.items()) + f" (calibrated: {c['heldout_gap_proposed']:.4g})."]
    if c.get("refined"):
        r = c["refined"]
        if r.get("held_fixed") or r.get("folded"):
            L += ["", f"Refined with the best screened effect held fixed on top ({r['held_fixed'] or 'none'})"
                  + (f" and the screened contact_softness folded into the solref time constant ({r['folded']})"
                     if r.get("folded") else "") + ": "
                  + (f"the settings moved (first pass: {'; '.join(r['first_pass']) or 'none'})." if r["settings_moved"]
                     else "the settings did not move.")]
            L += _refine_groups(r)
        else:
            L += ["", "No library effect lowered the training loss on top of the first calibration (screen): "
                  "not refined."]
        alt = r.get("contact_effect_start") or {}
        if "heldout_gap" in alt:  # the second start ran (the share reached the threshold)
            L += ["", f"Calibrated again from the start with {alt['held_fixed']} held fixed (a contact effect the "
                  "settings can imitate, screened on the nominal model): held-out gap "
                  f"{alt['heldout_gap']:.4g} against {alt['heldout_gap_other']:.4g}, "
                  + ("adopted: the effect is scored on these settings." if alt["adopted"] else "not adopted.")]
    chk = c.get("recheck") or {}
    if chk.get("ran"):
        L += ["", f"Checked again with the best hypothesis ({', '.join(chk['best'])}) held fixed on top, which the "
              f"refinement had not held ({', '.join(chk['refinement_held']) or 'none'}): held-out gap with it "
              f"{chk['heldout_gap']:.4g} against {chk['heldout_gap_before']:.4g} on the settings before (sign-flip p "
              f"{chk.get('p_value', float('nan')):.2g}), "
              + ("adopted: the settings above are these, and the effects were scored again on them."
                 if chk["adopted"] else "not adopted.")]
    L += ["", f"{c['evaluations']} replays of the training split, {c['seconds']:.0f} s. What calibration can and cannot "
          "tell apart: docs/gap.md (a softer ground is a longer solref time constant; contact parameters can take up "
          "part of a payload or of ground friction).", ""]
    return L


def residual_section(d: dict[str, Any], files: dict[str, str]) -> list[str]:
    """The STRIDE residual on top of the best hypothesis: how much of what the library leaves it
    explains held-out, and where it concentrates (per dof, contact phase, state bins)."""
    res = d.get("residual")
    L = ["", "## What the library leaves (STRIDE residual on top)", ""]
    if not res:
        when = d["config"].get("residual", {}).get("when", "unexplained")
        return L + [f"Not fitted (verdict: {d['verdict']['verdict']}; `residual.when = {when}`: fitted when the "
                    "verdict is 'unexplained by the library', or always with `--residual.when always`).", ""]
    cfg, c = res["config"], res["concentration"]
    L += [f"A conditional flow-matching model of the generalised force that the best hypothesis's simulator "
          f"({' + '.join(res['on_top_of']) or 'nominal'}) misses, given (q, qd, tau); trained on "
          f"{res['n_train']} one-step replays ({cfg['steps']} steps, MLP {cfg['hidden']}x{cfg['depth']}, "
          f"flow-matching loss {res['fm_loss_first']:.3g} → {res['fm_loss_last']:.3g}, {res['seconds']:.1f} s), "
          f"scored with its central sample (NFE {cfg['nfe']}) on {res['n_heldout']} held-out replays.", "",
          f"**Held-out one-step gap left by the best: {res['heldout_gap_left']:.4g} → {res['heldout_gap_after']:.4g} "
          f"with the residual: {res['explained']:.1%} explained** ({res['explained_above_floor']:.1%} above the "
          f"noise floor {res['noise_floor']:.3g}; on the training split {res['train_explained']:.1%}).", ""]
    if "residual" in files:
        L += [f"![residual]({files['residual']})", ""]
    L += ["| dof | mean abs force (N or N m) | fitted RMS (scaled) | left RMS (scaled) | share | "
          "acc RMSE left → after (rad/s² or m/s²) |", "|---|---|---|---|---|---|"]
    for n, r in c["per_dof"].items():
        L.append(f"| {n} | {r['force_mean_abs']:.4g} | {r['rms_scaled']:.3g} | {r['left_rms_scaled']:.3g} | "
                 f"{r['share']:.1%} | {res['one_step_acc_rmse_left'][n]:.4g} → {res['one_step_acc_rmse_after'][n]:.4g} |")
    if c["per_foot_phase"]:
        L += ["", "Contact phase per foot (fitted / left scaled RMS; x: fitted RMS over its mean):", "",
              "| foot | swing | stance | touchdown | liftoff |", "|---|---|---|---|---|"]
        for foot, rows in c["per_foot_phase"].items():
            cells = [f"{_fmt(rows[p]['rms'], 3)} / {_fmt(rows[p]['left_rms'], 3)} ({_fmt(rows[p]['ratio'], 2)}x, "
                     f"n={rows[p]['count']})" for p in ("swing", "stance", "touchdown", "liftoff")]
            L.append(f"| {foot} | " + " | ".join(cells) + " |")
    if c.get("base_speed_bins"):
        L += ["", "| base speed (m/s) | n | fitted RMS | left RMS | x mean |", "|---|---|---|---|---|"]
        L += [f"| {b['lo']:.2f}-{b['hi']:.2f} | {b['count']} | {b['rms']:.3g} | {b['left_rms']:.3g} | {b['ratio']:.2f} |"
              for b in c["base_speed_bins"]]
    L += ["", "Largest bin of each joint's own fitted correction (at least 10 samples; x: its RMS over the "
          "joint's mean):", "", "| joint | velocity bin (rad/s) | x | position bin from home (rad) | x |",
          "|---|---|---|---|---|"]
    for j in c["joint_velocity_bins"]:
        cells = []
        for key in ("joint_velocity_bins", "joint_position_bins"):
            rows = [b for b in c[key][j] if b["count"] >= 10]
            b = max(rows, key=lambda b: b["rms"], default=None)
            cells += [f"{b['centre']:+.2f}", f"{b['ratio']:.2f}"] if b else ["-", "-"]
        L.append(f"| {j} | " + " | ".join(cells) + " |")
    return L + [""]


def write(d: dict[str, Any], out_dir: str | os.PathLike, command: str | None = None) -> pathlib.Path:
    """Writes ``diagnosis.json``, ``report.md`` and the plots into ``out_dir``."""
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files = plots(d, out)
    io.atomic_write_text(out / "diagnosis.json", json.dumps(d, indent=1, default=json_default))
    io.atomic_write_text(out / "report.md", markdown(d, files, command))
    return out / "report.md"


def json_default(x):
    """``json.dumps``'s ``default`` for the diagnosis: arrays as lists, numpy scalars as numbers."""
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.generic):
        return x.item()
    return str(x)
