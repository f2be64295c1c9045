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
