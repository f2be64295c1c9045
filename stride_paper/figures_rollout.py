"""The rollout-error figures on the legged robots: error against horizon for the five models
(:mod:`stride_jax.eval.horizon`, or Table I's own numbers), and error and inference rate against
NFE, CFM vs DDPM residual, on Go1 (:mod:`stride_jax.eval.nfe`)."""

from __future__ import annotations

import dataclasses

import numpy as np

import jax

from stride_jax.eval import horizon, nfe
from stride_paper.figure_context import Context, device_text, split_ints, split_names
from stride_paper.figure_runs import horizon_config, legged_runs


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
        nfe.plot(curves, reference, ctx.out / "nfe_tradeoff.png", jax.devices()[0].device_kind,
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
        horizon.plot(table, ctx.out / "rollout_horizon.png",
                     ctx.title("Open-loop rollout error vs horizon (mean ± std over seeds"
                               + ("; from " + ", ".join(split_names(c.horizon_tables))
                                  if "table" in sources.values() else "") + ")"))
    result = {"table": table, "per_run": per_run, "missing_runs": missing, "source": sources,
              "tables": split_names(c.horizon_tables),
              "config": dataclasses.asdict(hcfg), "definition": horizon.__doc__.strip(),
              "figure": "rollout_horizon.png" if table else None}
    ctx.write("horizon", result)
    return result
