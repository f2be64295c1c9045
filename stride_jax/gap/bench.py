"""The blind benchmark: plant an effect the diagnosis is not told, diagnose, score.

Cases per robot: every library effect that applies at two magnitudes, pairs of effects, effects
outside the library, and a control with no effect; each on noise-free logs and on logs through a
real robot's sensors (:class:`~stride_jax.gap.real.SensorNoise`). Scores:

* top-1 accuracy: the verdict names exactly the planted effect(s) (single in-library cases);
* parameter error: |estimate - truth| / |truth - nominal| for correct single attributions;
* held-out gap shrink: one-step gap on the *noise-free* version of the held-out trajectories,
  nominal against the identified effect (the tool's own shrink on its noisy logs is reported
  beside it; there the noise floor caps it), and the same for the true parameter (the oracle);
* confident false attributions: a confident "explained" verdict naming anything but the truth
  (for out-of-library effects and the control: naming anything at all);
* the control must report "no significant gap".

``tiny`` runs the pendulum (minutes on a 2-core CPU); ``default`` runs the Go1.
"""

from __future__ import annotations

import dataclasses
import json
import os
import pathlib
import time
from typing import Any

import numpy as np

from stride_jax import io
from stride_jax.gap import diagnose, effects, fit, real
from stride_jax.sim import model


@dataclasses.dataclass(frozen=True)
class BenchConfig:
    """A benchmark preset.

    Attributes:
      robot: robot name.
      trajectories, steps: per case (control steps per trajectory).
      magnitudes: effect -> planted values (small, large; or one).
      pairs: planted pairs.
      out_of_library: planted effects the library lacks.
      noise: the noise settings to run (False: noise-free, True: :class:`SensorNoise`).
      diagnose: preset of the diagnosis.
      seed: of the planted runs.
      name: of the result files (``<out>/<name>.{md,json}``).
    """

    robot: str
    trajectories: int
    steps: int
    magnitudes: dict
    pairs: tuple
    out_of_library: tuple
    noise: tuple = (False, True)
    diagnose: str = "tiny"
    seed: int = 1
    name: str = "gap_bench"


PRESETS = {
    "tiny": BenchConfig(
        robot="pendulum", trajectories=8, steps=150,
        magnitudes={"damping": (0.15, 0.5), "frictionloss": (0.15, 0.5), "armature": (0.05, 0.2),
                    "delay": (1, 3), "torque_scale": (0.85, 0.6), "torque_limit": (0.7, 0.45),
                    "payload": (0.15, 0.4), "com_offset": ((0.03, 0, 0), (0, 0, 0.06)),
                    "deadzone": (0.3, 1.0)},
        pairs=(({"damping": 0.3, "delay": 2}), ({"payload": 0.3, "torque_scale": 0.8})),
        out_of_library=({"joint_stiffness": 3.0}, {"quadratic_drag": 0.05}),
        diagnose="tiny"),
    "default": BenchConfig(
        robot="go1", trajectories=10, steps=150,
        magnitudes={"damping": (0.5, 1.5), "frictionloss": (0.3, 0.8), "armature": (0.02, 0.06),
                    "delay": (2, 5), "torque_scale": (0.85, 0.65), "torque_limit": (0.6, 0.35),
                    "kp_scale": (0.7, 1.4), "ground_friction": (0.5, 0.3),
                    "contact_softness": (2.0, 4.0), "payload": (1.0, 2.5),
                    "com_offset": ((0.03, 0, 0), (0, 0.04, 0)), "deadzone": (0.02, 0.05)},
        pairs=(({"damping": 1.0, "delay": 3}), ({"payload": 2.0, "torque_scale": 0.8})),
        out_of_library=({"joint_stiffness": 10.0}, {"quadratic_drag": 0.02}),
        diagnose="default", name="gap_bench_go1"),
    # what fits in <= 15 min on a 2-core CPU: one magnitude of six effects (left out: armature,
    # torque_limit, kp_scale, contact_softness, com_offset, deadzone, the second magnitudes and
    # joint_stiffness), both pairs, one out-of-library effect, the control; 5 x 60-step trajectories
    "go1_small": BenchConfig(
        robot="go1", trajectories=5, steps=60,
        magnitudes={"damping": (1.5,), "frictionloss": (0.8,), "delay": (5,), "torque_scale": (0.65,),
                    "payload": (2.5,), "ground_friction": (0.3,)},
        pairs=(({"damping": 1.0, "delay": 3}), ({"payload": 2.0, "torque_scale": 0.8})),
        out_of_library=({"quadratic_drag": 0.02},),
        diagnose="fast", name="gap_bench_go1"),
}


def cases(cfg: BenchConfig) -> list[dict[str, Any]]:
    """Every planted case: ``{"kind", "applied"}`` (kind: single, pair, out_of_library, control)."""
    out = [{"kind": "control", "applied": {}}]
    for name, mags in cfg.magnitudes.items():
        out += [{"kind": "single", "applied": {name: v}} for v in mags]
    out += [{"kind": "pair", "applied": dict(p)} for p in cfg.pairs]
    out += [{"kind": "out_of_library", "applied": dict(p)} for p in cfg.out_of_library]
    return out


def _vec(x) -> np.ndarray:
    return np.atleast_1d(np.asarray(x, float))


def score_case(sm, case: dict, result: dict, clean_heldout: list, cfg_d: diagnose.DiagnoseConfig
               ) -> dict[str, Any]:
    """Scores one diagnosis against the planted truth."""
    v = result["verdict"]
    planted = set(case["applied"])
    named = set(v["effects"]) if v["verdict"] == "explained" else set()
    row: dict[str, Any] = {"kind": case["kind"], "planted": {k: _vec(x).tolist() for k, x in case["applied"].items()},
                           "verdict": v["verdict"], "named": sorted(named), "confident": bool(v["confident"]),
                           "seconds": result["seconds"]}
    row["correct"] = (named == planted) if case["kind"] in ("single", "pair") else (not named)
    in_lib = case["kind"] in ("single", "pair")
    row["confident_false"] = bool(v["confident"] and named and (not in_lib or named != planted))
    wh = result.get("which")
    if wh:
        best = wh["ranking"][0]
        row["best"] = {"effects": best["effects"], "params": best["params"], "lo": best["param_lo"],
                       "hi": best["param_hi"], "explained": best["explained"]}
        row["tool_shrink"] = result["how_far"]["shrink"]
        row["tool_kstep_shrink"] = result["how_far"]["kstep_shrink"]
        # shrink on the noise-free held-out trajectories: nominal vs identified vs oracle
        data = fit.make_data(clean_heldout)
        scale = diagnose.scale_of(sm, data)
        g = lambda applied: fit.gap(fit.residual(sm, effects.build(sm, applied), data, scale))
        g0 = g({})
        if g0 > 0:
            row["clean_shrink"] = 1 - g({k: _vec(x) for k, x in best["params"].items()}) / g0
            if in_lib:
                row["oracle_shrink"] = 1 - g({k: _vec(x) for k, x in case["applied"].items()}) / g0
        res = result.get("residual")
        if res:  # the STRIDE residual on top of the best: share of the held-out gap left it explains
            row["residual_explained"] = res["explained"]
            row["residual_explained_above_floor"] = res["explained_above_floor"]
            row["residual_peak"] = res["concentration"]["summary"]
        if row["correct"] and case["kind"] == "single":
            (name,) = planted
            truth, est = _vec(case["applied"][name]), _vec(best["params"][name])
            nom = _vec(effects.ALL[name].nominal)
            row["param_error"] = float(np.linalg.norm(est - truth) / max(np.linalg.norm(truth - nom), 1e-12))
    return row


def summary(rows: list[dict]) -> dict[str, Any]:
    out = {}
    for noisy in (False, True):
        rs = [r for r in rows if r["noisy"] == noisy]
        if not rs:
            continue
        singles = [r for r in rs if r["kind"] == "single"]
        pairs = [r for r in rs if r["kind"] == "pair"]
        ool = [r for r in rs if r["kind"] == "out_of_library"]
        ctrl = [r for r in rs if r["kind"] == "control"]
        med = lambda xs: float(np.median(xs)) if xs else None
        out["noisy" if noisy else "noise_free"] = {
            "top1_single": float(np.mean([r["correct"] for r in singles])) if singles else None,
            "top1_pairs": float(np.mean([r["correct"] for r in pairs])) if pairs else None,
            "median_param_error_single": med([r["param_error"] for r in singles if "param_error" in r]),
            "median_clean_shrink_single": med([r["clean_shrink"] for r in singles if "clean_shrink" in r]),
            "min_clean_shrink_single": min([r["clean_shrink"] for r in singles if "clean_shrink" in r], default=None),
            "median_oracle_shrink_single": med([r["oracle_shrink"] for r in singles if "oracle_shrink" in r]),
            "median_tool_shrink_single": med([r["tool_shrink"] for r in singles if "tool_shrink" in r]),
            "confident_false_attributions": int(sum(r["confident_false"] for r in rs)),
            "confident_false_out_of_library": int(sum(r["confident_false"] for r in ool)),
            "out_of_library_verdicts": [r["verdict"] for r in ool],
            "out_of_library_residual_explained": [r.get("residual_explained") for r in ool],
            "control_verdict": [r["verdict"] for r in ctrl],
            "cases": len(rs),
        }
    return out


def markdown(cfg: BenchConfig, rows: list[dict], summ: dict, command: str, seconds: float) -> str:
    L = [f"# Sim-to-real gap: blind benchmark ({cfg.robot})", "", f"Command: `{command}`", "",
         f"{cfg.trajectories} trajectories x {cfg.steps} control steps per case; diagnosis preset "
         f"`{cfg.diagnose}`; {len(rows)} diagnoses in {seconds / 60:.1f} min. Targets (issue 5): top-1 >= 90% on "
         "single in-library effects; held-out gap shrink >= 95% noise-free, >= 80% noisy; no confident false "
         "attribution on out-of-library effects; the control reports no significant gap.", "",
         "Shrink is measured on the noise-free version of the held-out trajectories (the tool's own "
         "shrink on noisy logs is capped by the noise floor and reported per case).", "",
         "| metric | noise-free | noisy |", "|---|---|---|"]
    keys = ["top1_single", "top1_pairs", "median_param_error_single", "median_clean_shrink_single",
            "min_clean_shrink_single", "median_oracle_shrink_single", "median_tool_shrink_single",
            "confident_false_attributions", "confident_false_out_of_library", "out_of_library_verdicts",
            "out_of_library_residual_explained", "control_verdict"]
    f = lambda x: "-" if x is None else (f"{x:.3g}" if isinstance(x, float) else str(x))
    for k in keys:
        L.append(f"| {k} | {f(summ.get('noise_free', {}).get(k))} | {f(summ.get('noisy', {}).get(k))} |")
    L += ["", "Residual: share of the held-out gap left by the best hypothesis that the STRIDE residual fitted on "
          "top explains (fitted when the verdict is 'unexplained by the library').", "",
          "| noise | kind | planted | verdict | named | confident | best fit | clean shrink | oracle | tool shrink | param err "
          "| residual |",
          "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        b = r.get("best", {})
        L.append(f"| {'noisy' if r['noisy'] else 'clean'} | {r['kind']} | {r['planted']} | {r['verdict']} | "
                 f"{'+'.join(r['named']) or '-'} | {r['confident']} | {b.get('params', '-')} | "
                 f"{f(r.get('clean_shrink'))} | {f(r.get('oracle_shrink'))} | {f(r.get('tool_shrink'))} | "
                 f"{f(r.get('param_error'))} | {f(r.get('residual_explained'))} |")
    return "\n".join(L) + "\n"


def run(cfg: BenchConfig, out_dir: str | os.PathLike = "results", command: str = "",
        log=print) -> dict[str, Any]:
    """Runs the benchmark and writes ``<out_dir>/<name>.{md,json}``."""
    sm = model.load(cfg.robot)
    dcfg = diagnose.PRESETS[cfg.diagnose]
    t0 = time.time()
    rows = []
    for c in cases(cfg):
        for noisy in cfg.noise:
            clean, logged = real.generate(sm, c["applied"], cfg.trajectories, cfg.steps, cfg.seed,
                                          real.SensorNoise() if noisy else None)
            res = diagnose.diagnose(sm, logged, dcfg, log=lambda s: None)
            held = [t for t in clean if t.name in set(res["heldout"])]
            row = score_case(sm, c, res, held, dcfg) | {"noisy": noisy}
            rows.append(row)
            log(f"[{time.time() - t0:6.0f} s] {'noisy' if noisy else 'clean'} {c['kind']:14s} {row['planted']} -> "
                f"{row['verdict']} {row['named']} conf={row['confident']} shrink={row.get('clean_shrink')}")
    summ = summary(rows)
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    seconds = time.time() - t0
    result = {"command": command, "config": dataclasses.asdict(cfg), "summary": summ, "cases": rows,
              "seconds": seconds}
    io.atomic_write_text(out / f"{cfg.name}.json", json.dumps(result, indent=1, default=float))
    io.atomic_write_text(out / f"{cfg.name}.md", markdown(cfg, rows, summ, command, seconds))
    log(json.dumps(summ, indent=1))
    return result
