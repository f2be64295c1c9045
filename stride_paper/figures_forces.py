"""The contact-force figure: predicted vs true vertical ground reaction force per foot, read from
each structured model's residual through the contact Jacobians, Go1 per gait and G1
(:mod:`stride_jax.eval.contact`)."""

from __future__ import annotations

import dataclasses

from stride_jax.dynamics import models as models_lib
from stride_jax.eval import contact
from stride_jax.eval import runs as runs_lib
from stride_paper.figure_context import Context, split_names
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
        contact.plot(robot, arrays, {n: ps[0] for n, ps in per_model.items()}, ctx.out / png,
                     ctx.title(f"{robot}: vertical GRF from the residual (seed 0; legend: "
                               "mean |error| of that behaviour)"))
        result["robots"][robot] = {"table": numbers, "per_seed": per_model, "figure": png}
    ctx.write("forces", result)
    return result
