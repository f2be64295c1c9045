"""Accuracy and speed against the number of function evaluations (the paper's inference figure).

For the generative residuals of the structured models -- STRIDE's conditional flow (Euler steps)
and LNN + Diffusion's DDPM (DDIM-strided levels) -- trained once with their default NFE and
sampled at test time with each NFE of a grid:

* **rollout error**: the cumulative ``H``-step open-loop error of :mod:`stride_jax.eval.horizon`;
* **inference rate** (calls/s): one over the median wall time of a jitted call, after a warm-up
  call, on the device the command ran on, of (a) the **residual sampler** alone (one sample of
  ``eps`` from its context: what NFE changes; the paper's comparison) and (b) the **model**'s
  acceleration ``qdd = f_LNN(q, qd, tau) + M^-1 eps`` (prior plus one residual sample: the unit
  a controller calls per integration substep). Each for one state per call (latency) and for a
  batch of states per call (vmapped, as a sampling planner calls it; the plotted rates -- at one
  state a small network's call time is dispatch overhead, not NFE). DeLaN (a deterministic
  residual, no NFE) is the reference.
"""

from __future__ import annotations

import json
import pathlib

import jax
import jax.numpy as jnp
import numpy as np

from stride_jax.dynamics import mlp, models, stride
from stride_jax.eval import horizon
from stride_jax.eval.runs import LoadedRun
from stride_jax.timing import median_time


def _states(run: LoadedRun, batch: int):
    """``batch`` test states ``(q, qd, tau)`` (cycled when the split has fewer)."""
    test = run.ds.split("test")
    idx = np.argwhere(test["valid"])
    idx = idx[np.arange(batch) % len(idx)]
    return tuple(np.asarray(test[k][idx[:, 0], idx[:, 1]], np.float32)
                 for k in ("q", "qd", "tau"))


def _residual_fn(run: LoadedRun):
    """``(params, q, qd, tau, key, nfe) -> eps [nv]``: the run's residual alone, rebuilt from
    its ``model.json`` (the Model interface only exposes it together with the prior)."""
    d = json.loads((run.path / "model.json").read_text())
    c = d["config"]
    cfg = stride.StructuredConfig(**dict(c, net=mlp.MLPConfig(**c["net"])))
    sc = stride.Scales(**{k: jnp.asarray(v, jnp.float32) for k, v in d["scales"].items()})
    kind = models.MODELS[d["name"]][1]
    return lambda p, q, qd, tau, k, nfe: stride.residual_force(p, run.spec, cfg, kind, q, qd,
                                                               tau, k, nfe, sc)


def inference_time(run: LoadedRun, nfe: int | None, repeats: int, batch: int = 1,
                   what: str = "model") -> float:
    """Median wall time (s) of one jitted call on ``batch`` test states at once (vmapped; one
    latent sample each) of the model's acceleration (``what='model'``) or of its residual
    sampler alone (``'residual'``)."""
    if what == "model":
        one = lambda p, q, qd, tau, k: run.model.acceleration(p, q, qd, tau, k, nfe)
    elif what == "residual":
        res = _residual_fn(run)
        one = lambda p, q, qd, tau, k: res(p, q, qd, tau, k, nfe)
    else:
        raise ValueError(f"what must be 'model' or 'residual', got {what!r}")
    fn = jax.jit(jax.vmap(one, in_axes=(None, 0, 0, 0, 0)))
    q, qd, tau = _states(run, batch)
    keys = jax.random.split(jax.random.key(0), batch)
    return median_time(lambda: fn(run.params, q, qd, tau, keys).block_until_ready(), repeats)


def rates(run: LoadedRun, nfe: int | None, repeats: int, batch: int) -> dict:
    """Calls per second (Hz) of the model and of its residual sampler, at one state per call
    and at ``batch`` states per call."""
    out = {"batch": batch}
    for what in ("model", "residual"):
        out[f"{what}_hz"] = 1.0 / inference_time(run, nfe, repeats, 1, what)
        out[f"{what}_batch_hz"] = 1.0 / inference_time(run, nfe, repeats, batch, what)
    return out


RATES = ("model_hz", "model_batch_hz", "residual_hz", "residual_batch_hz")


def sweep(runs: list[LoadedRun], nfes: list[int], cfg: horizon.HorizonConfig,
          cache_dir: pathlib.Path, repeats: int, batch: int, log=print) -> dict:
    """Per NFE: rollout error per seed (and its mean/std) and the inference rates (timed on the
    first seed's run: the time does not depend on the parameters' values)."""
    out = {"nfe": list(nfes), "error_mean": [], "error_std": [], "error_per_seed": [],
           "diverged": [], **{k: [] for k in RATES}, "batch": batch}
    for nfe in nfes:
        per_seed = [horizon.evaluate(r, cfg, cache_dir, nfe) for r in runs]
        cums = np.array([p["cumulative"] for p in per_seed], np.float64)
        out["error_per_seed"].append(cums.tolist())
        out["error_mean"].append(float(np.nanmean(cums)))
        out["error_std"].append(float(np.nanstd(cums)))
        out["diverged"].append(float(np.mean([p["diverged"] for p in per_seed])))
        r = rates(runs[0], nfe, repeats, batch)
        for k in RATES:
            out[k].append(r[k])
        log(f"  {runs[0].model.name} NFE {nfe}: error {out['error_mean'][-1]:.3f} "
            f"± {out['error_std'][-1]:.3f}; {batch} states per call: residual "
            f"{r['residual_batch_hz']:.0f} Hz, model {r['model_batch_hz']:.0f} Hz")
    out["seeds"] = [r.seed for r in runs]
    out["trained_nfe"] = runs[0].nfe
    return out
