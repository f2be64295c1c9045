"""Residual allocation on the bouncing pendulum (the paper's Sec. III-F: 6.5% vs 78.8%).

A structured model splits its acceleration into the Lagrangian prior and the residual,
``qdd = f_LNN + M^-1 eps``. On held-out steps of the bouncing pendulum (a wall the bob strikes),
the residual's share of the predicted acceleration is taken in **free swing** (the bob touches
nothing) and at **impacts** (the bob carries a wall contact force), with the share of
:func:`stride_jax.eval.forces.residual_share`: ``|M^-1 eps| / (|f_LNN| + |M^-1 eps|)``, in [0, 1]
(for one dof the per-dof normalisation cancels). The same formula applied to the simulator's own
split -- ``tau - qfrc_bias`` for the prior, ``qfrc_passive + qfrc_constraint + qfrc_external`` for
the residual -- gives what a perfect split would report (``truth``). The paper's wording ("the
residual contributes 6.5% of the predicted acceleration magnitude") fits this share; we also
report ``|M^-1 eps| / |qdd|`` (``ratio_to_total``, its median: it is unbounded where the two
parts cancel).
"""

from __future__ import annotations

import dataclasses
import pathlib

import jax
import jax.numpy as jnp
import numpy as np

from stride_jax.eval import forces
from stride_jax.eval.runs import LoadedRun, valid_steps

PAPER = {"free": 0.065, "contact": 0.788}


@dataclasses.dataclass(frozen=True)
class AllocationConfig:
    """Attributes:
      steps: held-out steps drawn per region (at most; all when fewer exist).
      samples: latent samples per step of a stochastic residual.
      seed: steps and latents.
    """

    steps: int = 2048
    samples: int = 8
    seed: int = 0


def terms(run: LoadedRun, q, qd, tau, samples: int, key: jax.Array) -> dict[str, np.ndarray]:
    """``{'prior', 'residual'}``, each ``[S, N, nv]``: the model's split at ``N`` states."""
    model = run.model
    s = samples if model.stochastic else 1

    @jax.jit
    def fn(params, q, qd, tau, keys):
        one = lambda q, qd, tau, k: model.terms(params, q, qd, tau, k)
        return jax.vmap(lambda k: jax.vmap(one)(q, qd, tau, jax.random.split(k, len(q))))(keys)

    t = fn(run.params, jnp.asarray(q), jnp.asarray(qd), jnp.asarray(tau), jax.random.split(key, s))
    return {k: np.asarray(t[k]) for k in ("prior", "residual")}


def _stats(share: np.ndarray) -> dict:
    """Mean over steps per sample ``share [S, N]`` -> mean, spread over samples, median."""
    per_sample = share.mean(1)
    return {"mean": float(per_sample.mean()), "sample_spread": float(per_sample.std()),
            "median": float(np.median(share)), "steps": int(share.shape[1])}


def evaluate(run: LoadedRun, cfg: AllocationConfig) -> tuple[dict, dict]:
    """``(numbers, arrays)`` for one run: shares per region, for the model and the truth."""
    if run.model.terms is None:
        raise ValueError(f"{run.model.name} has no prior/residual split")
    test, train = run.ds.split("test"), run.ds.split("train")
    contact = test["foot_contact"].any(-1)
    qdd_scale = np.asarray(train["qdd"][train["valid"]].std(0)) + 1e-6
    key = jax.random.key(cfg.seed)
    numbers, arrays = {"seed": run.seed, "steps_done": run.steps_done}, {}
    for region, mask in (("free", ~contact), ("contact", contact)):
        idx = valid_steps(test, cfg.steps, cfg.seed, mask)
        if len(idx) == 0:
            numbers[region] = None
            continue
        pick = lambda k: np.asarray(test[k][idx[:, 0], idx[:, 1]], np.float32)
        t = terms(run, pick("q"), pick("qd"), pick("tau"), cfg.samples,
                  jax.random.fold_in(key, int(region == "contact")))
        share = np.stack([forces.residual_share(p, r, qdd_scale)
                          for p, r in zip(t["prior"], t["residual"])])  # [S, N]
        total = np.linalg.norm((t["prior"] + t["residual"]) / qdd_scale, axis=-1)
        ratio = np.linalg.norm(t["residual"] / qdd_scale, axis=-1) / np.maximum(total, 1e-9)
        true_prior = pick("tau") - pick("qfrc_bias")
        true_res = pick("qfrc_passive") + pick("qfrc_constraint") + pick("qfrc_external")
        # One dof: M^-1 is a positive scalar and cancels in the share.
        true_share = forces.residual_share(true_prior, true_res, np.ones_like(qdd_scale))
        numbers[region] = {**_stats(share), "ratio_to_total_median": float(np.median(ratio)),
                           "truth_mean": float(true_share.mean()),
                           "truth_median": float(np.median(true_share))}
        arrays[region] = {"share": share.ravel(), "truth": true_share}
    # One held-out episode with impacts, for the time series.
    e = int(np.argmax((contact & test["valid"]).sum(1)))
    steps = np.flatnonzero(test["valid"][e])
    pick = lambda k: np.asarray(test[k][e, steps], np.float32)
    t = terms(run, pick("q"), pick("qd"), pick("tau"), cfg.samples, jax.random.fold_in(key, 7))
    arrays["episode"] = {"t": steps * run.ds.meta["ctrl_dt"], "qdd": pick("qdd")[:, 0],
                         "prior": t["prior"][..., 0], "residual": t["residual"][..., 0],
                         "contact": contact[e, steps], "episode": e}
    return numbers, arrays


def over_seeds(per_seed: list[dict]) -> dict:
    """Mean and std over seeds of each region's mean share."""
    out = {}
    for region in ("free", "contact"):
        vals = [p[region]["mean"] for p in per_seed if p.get(region)]
        truth = [p[region]["truth_mean"] for p in per_seed if p.get(region)]
        out[region] = ({"mean": float(np.mean(vals)), "std": float(np.std(vals)), "n": len(vals),
                        "truth": float(np.mean(truth)), "paper": PAPER[region]} if vals else None)
    return out


def plot(numbers: dict, arrays: dict, path: pathlib.Path, title: str = "") -> pathlib.Path:
    """(a) the residual's share in free swing and at impacts: ours (mean +- std over seeds), the
    simulator's split and the paper's; (b) its distribution over steps; (c) one held-out
    episode: true acceleration, the prior and the residual, impacts shaded."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

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
    if title:
        fig.suptitle(title, fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
