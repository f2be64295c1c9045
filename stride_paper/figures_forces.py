"""The contact-force figure: predicted vs true vertical ground reaction force per foot, read from
each structured model's residual through the contact Jacobians, Go1 per gait and G1
(:mod:`stride_jax.eval.contact`)."""

from __future__ import annotations

import dataclasses
import pathlib

from stride_jax.dynamics import models as models_lib
from stride_jax.eval import contact
from stride_jax.eval import runs as runs_lib
from stride_jax.eval.horizon import COLORS, LABELS
from stride_paper.figure_context import Context, pyplot, save, split_names
from stride_paper.figure_runs import legged_runs


def part_forces(ctx: Context) -> dict:
    c = ctx.cfg
    fcfg = contact.ContactConfig(steps=c.force_steps, window=c.force_window,
                                 samples=c.force_samples, seed=c.seed)
    names = [n for n in split_names(c.models) if models_lib.MODELS[n][0] == "structured"]
    result = {"config": dataclasses.asdict(fcfg), "definition": contact.__doc__.strip(),
              "robots": {}, "missing_runs": []}
    for robot in split_names(c.robots):
        runs, missing = legged_runs(ctx, robot, names)
        result["missing_runs"] += missing
        if not runs:
            continue
        behaviours = contact.behaviours(robot, next(iter(runs.values()))[0].ds.arrays)[0]
        numbers, arrays, per_model = {}, {}, {}
        for name, rs in runs.items():
            ctx.log(f"contact forces: {name} on {robot} ({len(rs)} seeds)")
            per_seed = []
            for i, run in enumerate(rs):
                key = runs_lib.cache_key(run, **dataclasses.asdict(fcfg))
                path = ctx.cache / "forces" / f"{run.path.parent.name}_{run.path.name}.json"
                if i == 0:  # the plotted run: its arrays are needed, so no cache
                    num, arr = contact.evaluate(run, fcfg)
                    arrays[name] = arr
                else:
                    num = runs_lib.cached(path, key, lambda run=run: contact.evaluate(run, fcfg)[0])
                per_seed.append(num)
            per_model[name] = per_seed
            numbers[name] = contact.over_seeds(per_seed, behaviours)
        png = f"contact_forces_{robot}.png"
        plot_contact(robot, arrays, {n: ps[0] for n, ps in per_model.items()}, ctx.out / png,
                     ctx.title(f"{robot}: vertical GRF from the residual (seed 0; legend: "
                               "mean |error| of that behaviour)"))
        result["robots"][robot] = {"table": numbers, "per_seed": per_model, "figure": png}
    ctx.write("forces", result)
    return result


def plot_contact(robot: str, arrays: dict[str, dict], numbers: dict[str, dict], path: pathlib.Path,
         title: str = "") -> pathlib.Path:
    """Rows: behaviours (Go1: the four gaits; G1: stepping); columns: feet. The truth in black,
    each model's force from its residual (mean over samples, with their range)."""
    plt = pyplot()

    models = list(arrays)
    first = arrays[models[0]]
    rows = list(first) if robot == "go1" else [b for b in ("step in place", "weight shift",
                                                            "stand") if b in first][:1]
    feet = numbers[models[0]]["feet"]
    fig, ax = plt.subplots(len(rows), len(feet), figsize=(max(3.6 * len(feet), 9.0),
                                                          2.4 * len(rows) + 0.8),
                           squeeze=False, sharex="row")
    for i, b in enumerate(rows):
        for j, foot in enumerate(feet):
            a = ax[i, j]
            w = first[b]
            a.plot(w["t"], w["true"][:, j], "k", lw=1.4, label="truth")
            for name in models:
                p = arrays[name][b]["pred"][:, :, j]  # [S, T]
                color = COLORS.get(name)
                err = numbers[name].get(b, {}) or {}
                label = (f"{LABELS.get(name, name)} "
                         f"({err.get('per_foot', {}).get(foot, float('nan')):.0f} N)")
                a.plot(w["t"], p.mean(0), color=color, lw=1, label=label)
                if len(p) > 1:
                    a.fill_between(w["t"], p.min(0), p.max(0), color=color, alpha=0.15, lw=0)
            top = max(float(w["true"].max()), 1.0)  # wild samples must not hide the truth
            a.set_ylim(-0.4 * top, 1.6 * top)
            a.set_title(f"{b}: {foot} (episode {w['episode']}, {w['split']})", fontsize=8)
            if j == 0:
                a.set_ylabel("vertical GRF (N)")
            if i == len(rows) - 1:
                a.set_xlabel("t (s)")
            a.legend(fontsize=6)
    return save(fig, path, title, dpi=110)
