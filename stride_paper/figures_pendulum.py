"""The pendulum figures: the phase portrait near the upright (truth vs ONN, DeLaN, STRIDE;
:mod:`stride_jax.eval.phase`) and STRIDE's residual allocation in free swing vs at impacts on
the bouncing pendulum (:mod:`stride_jax.eval.allocation`)."""

from __future__ import annotations

import dataclasses
import pathlib

import numpy as np

from stride_jax.eval import allocation, phase
from stride_jax.jobs.show import plot_phase
from stride_paper.figure_context import Context, pyplot, save, split_names
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
            plot_phase(arrays, numbers, ctx.out / "phase_portrait.png",
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
    plot_allocation(agg, first, ctx.out / "residual_allocation.png",
                    ctx.title("Residual allocation (STRIDE, bouncing pendulum)"))
    result = {"share": agg, "per_seed": per_seed, "definition": allocation.__doc__.strip(),
              "config": dataclasses.asdict(acfg), "figure": "residual_allocation.png"}
    ctx.write("allocation", result)
    return result


def plot_allocation(numbers: dict, arrays: dict, path: pathlib.Path,
                    title: str = "") -> pathlib.Path:
    """(a) the residual's share in free swing and at impacts: ours (mean +- std over seeds), the
    simulator's split and the paper's; (b) its distribution over steps; (c) one held-out
    episode: true acceleration, the prior and the residual, impacts shaded."""
    plt = pyplot()

    fig, ax = plt.subplots(1, 3, figsize=(15, 4), gridspec_kw={"width_ratios": [1, 1, 2]})
    regions = [r for r in ("free", "contact") if numbers.get(r)]
    x = np.arange(len(regions))
    w = 0.27
    ax[0].bar(x - w, [100 * numbers[r]["mean"] for r in regions], w,
              yerr=[100 * numbers[r]["std"] for r in regions], color="C3", label="STRIDE (ours)")
    ax[0].bar(x, [100 * numbers[r]["truth"] for r in regions], w, color="k", alpha=0.4,
              label="simulator's split")
    ax[0].bar(x + w, [100 * numbers[r]["paper"] for r in regions], w, color="C1", alpha=0.7,
              label="paper")
    ax[0].set_xticks(x, ["free swing" if r == "free" else "impacts" for r in regions])
    ax[0].set(ylabel="residual share of |qdd| (%)", ylim=(0, 100),
              title="residual allocation, bouncing pendulum")
    ax[0].legend(fontsize=7)
    bins = np.linspace(0, 1, 41)
    for r, c in (("free", "C0"), ("contact", "C3")):
        if r in arrays:
            ax[1].hist(arrays[r]["share"], bins=bins, density=True, alpha=0.5, color=c,
                       label=f"{'free swing' if r == 'free' else 'impacts'} (model)")
            ax[1].hist(arrays[r]["truth"], bins=bins, density=True, histtype="step", color=c,
                       lw=1.5, label=f"{'free swing' if r == 'free' else 'impacts'} (simulator)")
    ax[1].set(xlabel="residual share", ylabel="density", title="share per held-out step")
    ax[1].legend(fontsize=7)
    ep = arrays["episode"]
    t = ep["t"]
    ax[2].plot(t, ep["qdd"], "k", lw=1.2, label="true qdd")
    ax[2].plot(t, ep["prior"].mean(0), color="C0", lw=1, label="prior f_LNN")
    res = ep["residual"]
    ax[2].plot(t, res.mean(0), color="C3", lw=1, label="residual M^-1 eps (mean)")
    if len(res) > 1:
        ax[2].fill_between(t, res.min(0), res.max(0), color="C3", alpha=0.2, lw=0,
                           label="residual samples (range)")
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 1.0
    for i, tc in enumerate(t[ep["contact"]]):  # impacts last a step or two: mark each
        ax[2].axvspan(tc - dt / 2, tc + dt / 2, color="orange", alpha=0.4, lw=0,
                      label="wall contact" if i == 0 else None)
    ax[2].set(yscale="symlog", xlabel="t (s)", ylabel="rad/s² (symlog)",
              title=f"held-out episode {ep['episode']}")
    ax[2].legend(fontsize=7, ncol=2)
    return save(fig, path, title, dpi=110)
