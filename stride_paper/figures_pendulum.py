"""The pendulum figures: the phase portrait near the upright (truth vs ONN, DeLaN, STRIDE;
:mod:`stride_jax.eval.phase`) and STRIDE's residual allocation in free swing vs at impacts on
the bouncing pendulum (:mod:`stride_jax.eval.allocation`)."""

from __future__ import annotations

import dataclasses

import numpy as np

from stride_jax.eval import allocation, phase
from stride_paper.figure_context import Context, split_names
from stride_paper.figure_runs import pendulum_runs


def part_phase(ctx: Context) -> dict:
    c = ctx.cfg
    names = tuple(split_names(c.phase_models))
    runs = pendulum_runs(ctx, "pendulum", names)
    pcfg = phase.PhaseConfig(grid=c.phase_grid, worlds=c.phase_worlds, samples=c.phase_samples,
                             seed=c.seed)
    per_seed = []
    for i in range(len(next(iter(runs.values())))):
        numbers, arrays = phase.evaluate({n: rs[i] for n, rs in runs.items()}, pcfg)
        per_seed.append(numbers)
        if i == 0:
            phase.plot(arrays, numbers, ctx.out / "phase_portrait.png",
                       ctx.title("Pendulum near the upright (seed 0)"))
    agg = {}
    for name in names:
        agg[name] = {k: {"mean": float(np.mean([p[name][k] for p in per_seed])),
                         "std": float(np.std([p[name][k] for p in per_seed])),
                         "n": len(per_seed)}
                     for k in ("field_rmse", "field_rmse_normalised", "w1_near",
                               "w1_near_over_floor", "spread_near")}
        agg[name]["steps_done"] = sorted({p[name]["steps_done"] for p in per_seed}, key=str)
    result = {"truth": per_seed[0]["truth"], "models": agg, "per_seed": per_seed,
              "residual": phase.RESIDUAL,
              "config": dataclasses.asdict(pcfg), "figure": "phase_portrait.png"}
    ctx.write("phase", result)
    return result


def part_allocation(ctx: Context) -> dict:
    c = ctx.cfg
    runs = pendulum_runs(ctx, "pendulum_bouncing", ("stride",))["stride"]
    acfg = allocation.AllocationConfig(steps=c.alloc_steps, samples=c.samples, seed=c.seed)
    per_seed, first = [], None
    for run in runs:
        numbers, arrays = allocation.evaluate(run, acfg)
        per_seed.append(numbers)
        first = first or arrays
    agg = allocation.over_seeds(per_seed)
    allocation.plot(agg, first, ctx.out / "residual_allocation.png",
                    ctx.title("Residual allocation (STRIDE, bouncing pendulum)"))
    result = {"share": agg, "per_seed": per_seed, "definition": allocation.__doc__.strip(),
              "config": dataclasses.asdict(acfg), "figure": "residual_allocation.png"}
    ctx.write("allocation", result)
    return result
