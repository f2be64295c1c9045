"""The rollout-error figures on the legged robots: error against horizon for the five models
(:mod:`stride_jax.eval.horizon`, or Table I's own numbers), and error and inference rate against
NFE, CFM vs DDPM residual, on Go1 (:mod:`stride_jax.eval.nfe`)."""

from __future__ import annotations

import dataclasses
import pathlib

import numpy as np

import jax

from stride_jax.eval import horizon, nfe
from stride_jax.eval.horizon import COLORS, LABELS
from stride_paper.figure_context import (Context, device_text, pyplot, save, split_ints,
                                         split_names)
from stride_paper.figure_runs import horizon_config, legged_runs

# A curve whose error passes this many times the median model's largest error is drawn clipped at
# that level, dashed (rollouts that diverge would otherwise squash every other curve).
OFF_SCALE = 30.0


def part_nfe(ctx: Context) -> dict:
    c = ctx.cfg
    names = [n for n in ("stride", "lnn_diffusion", "delan") if n in split_names(c.models)]
    runs, missing = legged_runs(ctx, "go1", names)
    hcfg = horizon_config(c)
    curves = {}
    for name, grid in (("stride", c.nfe_flow), ("lnn_diffusion", c.nfe_diffusion)):
        if runs.get(name):
            ctx.log(f"NFE sweep: {name} on go1 ({len(runs[name])} seeds)")
            curves[name] = nfe.sweep(runs[name], split_ints(grid), hcfg, ctx.cache,
                                     c.timing_repeats, c.timing_batch, ctx.log)
    reference = None
    if runs.get("delan"):
        per_seed = [horizon.evaluate(r, hcfg, ctx.cache) for r in runs["delan"]]
        cums = [p["cumulative"] for p in per_seed]
        reference = {"error_mean": float(np.mean(cums)), "error_std": float(np.std(cums)),
                     **nfe.rates(runs["delan"][0], None, c.timing_repeats, c.timing_batch),
                     "seeds": [r.seed for r in runs["delan"]]}
    if curves:
        plot_nfe(curves, reference, ctx.out / "nfe_tradeoff.png", jax.devices()[0].device_kind,
                 ctx.title(f"Go1: CFM vs DDPM residual, H = {c.horizon}"))
    result = {"curves": curves, "delan": reference, "missing_runs": missing,
              "horizon": dataclasses.asdict(hcfg), "definition": nfe.__doc__.strip(),
              "device": device_text(), "figure": "nfe_tradeoff.png" if curves else None}
    ctx.write("nfe", result)
    return result


def part_horizon(ctx: Context) -> dict:
    c = ctx.cfg
    hcfg = horizon_config(c)
    table, per_run, missing, sources = {}, {}, [], {}
    tables = dict(horizon.from_table(p) for p in split_names(c.horizon_tables))
    for robot in split_names(c.robots):
        if robot in tables:
            ctx.log(f"rollout errors on {robot}: read from its Table I file")
            per_run[robot], sources[robot] = tables[robot], "table"
        else:
            runs, miss = legged_runs(ctx, robot, split_names(c.models))
            missing += miss
            per_run[robot], sources[robot] = {}, "evaluated"
            for name, rs in runs.items():
                ctx.log(f"rollout errors: {name} on {robot} ({len(rs)} seeds)")
                per_run[robot][name] = [horizon.evaluate(r, hcfg, ctx.cache) for r in rs]
        table[robot] = {}
        for name, results in per_run[robot].items():
            if name not in split_names(c.models):
                continue
            row = horizon.over_seeds(results)
            ph = np.asarray(row["per_horizon_mean"])
            row["growth_last_over_half"] = float(ph[-1] / ph[len(ph) // 2 - 1])
            table[robot][name] = row
    table = {r: t for r, t in table.items() if t}
    if table:
        plot_horizon(table, ctx.out / "rollout_horizon.png",
                     ctx.title("Open-loop rollout error vs horizon (mean ± std over seeds"
                               + ("; from " + ", ".join(split_names(c.horizon_tables))
                                  if "table" in sources.values() else "") + ")"))
    result = {"table": table, "per_run": per_run, "missing_runs": missing, "source": sources,
              "tables": split_names(c.horizon_tables),
              "config": dataclasses.asdict(hcfg), "definition": horizon.__doc__.strip(),
              "figure": "rollout_horizon.png" if table else None}
    ctx.write("horizon", result)
    return result


def plot_horizon(table: dict[str, dict[str, dict]], path: pathlib.Path,
                 title: str = "") -> pathlib.Path:
    """One panel per robot: error vs horizon per model, mean over seeds with a +-1 std band.
    ``table[robot][model]`` is :func:`over_seeds` output."""
    plt = pyplot()

    robots = list(table)
    fig, axes = plt.subplots(1, max(len(robots), 1), figsize=(5.5 * max(len(robots), 1), 4),
                             squeeze=False)
    for ax, robot in zip(axes[0], robots):
        peaks = {n: float(np.nanmax(np.asarray(r["per_horizon_mean"], float)))
                 for n, r in table[robot].items()}
        finite = [p for p in peaks.values() if np.isfinite(p)]
        top = OFF_SCALE * float(np.median(finite)) if finite else np.inf
        for name, row in table[robot].items():
            m, s = np.asarray(row["per_horizon_mean"]), np.asarray(row["per_horizon_std"])
            h = np.arange(1, len(m) + 1)
            off = not np.isfinite(peaks[name]) or peaks[name] > top
            label = f"{LABELS.get(name, name)} ({len(row['seeds'])} seeds)"
            label += ", leaves the scale (diverging rollouts)" if off else ""
            ax.plot(h, np.minimum(m, top) if off else m, label=label, color=COLORS.get(name),
                    ls="--" if off else "-")
            if not off:
                ax.fill_between(h, m - s, m + s, alpha=0.2, color=COLORS.get(name))
        ax.set(title=robot, xlabel="horizon (control steps)",
               ylabel="normalised observation RMSE", yscale="log")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    return save(fig, path, title, dpi=120)


def plot_nfe(curves: dict[str, dict], reference: dict | None, path: pathlib.Path, device: str,
         title: str = "") -> pathlib.Path:
    """Left: rollout error against NFE per model (mean +- std over seeds; DeLaN's as a band).
    Right: calls/s against NFE, residual sampler (solid) and whole model (dash-dot), at the
    batched size; DeLaN's model rate as a line."""
    plt = pyplot()

    fig, ax = plt.subplots(1, 2, figsize=(11, 4.2))
    for name, c in curves.items():
        color = COLORS.get(name)
        label = LABELS.get(name, name)
        n, m, s = np.asarray(c["nfe"]), np.asarray(c["error_mean"]), np.asarray(c["error_std"])
        ax[0].errorbar(n, m, yerr=s, ls=":", marker="o", color=color, capsize=3, label=label)
        ax[1].plot(n, c["residual_batch_hz"], "-", marker="s", color=color,
                   label=f"{label}: residual sampler")
        ax[1].plot(n, c["model_batch_hz"], "-.", marker=".", color=color,
                   label=f"{label}: whole model")
    if reference is not None:
        d = COLORS["delan"]
        ax[0].axhline(reference["error_mean"], color=d, label="DeLaN (no NFE)")
        ax[0].axhspan(reference["error_mean"] - reference["error_std"],
                      reference["error_mean"] + reference["error_std"], color=d, alpha=0.15)
        ax[1].axhline(reference["model_batch_hz"], ls="-.", color=d, label="DeLaN: whole model")
    batch = next(iter(curves.values()))["batch"]
    ax[0].set(xscale="log", xlabel="NFE (residual network evaluations per sample)",
              ylabel="cumulative open-loop error (mean ± std over seeds)",
              title="rollout error vs NFE")
    errs = [e for c in curves.values() for e in c["error_mean"] if e is not None and e > 0]
    if errs and max(errs) > 20 * min(errs):  # a diverging low-NFE sampler flattens the rest
        ax[0].set_yscale("log")
    ax[1].set(xscale="log", yscale="log", xlabel="NFE",
              ylabel=f"calls/s, {batch} states per call", title=f"inference rate ({device})")
    for a in ax:
        a.grid(alpha=0.3)
        a.legend(fontsize=7)
    return save(fig, path, title, dpi=120)
