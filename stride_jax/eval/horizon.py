"""Open-loop rollout error against the horizon (the paper's Fig. "long-horizon rollout error").

The error at horizon ``h`` is the one of :mod:`stride_jax.eval.rollout` (normalised observation
RMSE, tangent-space differences): from the start of each test window a model rolls out the
logged commands, and the RMSE of ``[difference(q) / sigma_dq, (qd - qd_true) / sigma_qd]`` is
taken at every step. Here the parameters are an *argument* of the compiled program, so runs of
one model and robot that differ in their seed compile once (JAX's persistent cache).

Per run: the per-horizon error averaged over finite windows and samples, its spread over samples,
the cumulative error (sum over ``h = 1..H``, the Table I number), the fraction of diverged
(non-finite) rollouts, and the median window's errors (a few finite but exploding rollouts
dominate a mean; the median says what a typical window does). Over seeds: mean and std.
"""

from __future__ import annotations

import dataclasses
import json
import pathlib

import jax
import numpy as np

from stride_jax.eval import rollout
from stride_jax.eval.runs import LoadedRun, cache_key, cached


_VERSION = 2  # of the cached numbers: bump when summarise() changes


@dataclasses.dataclass(frozen=True)
class HorizonConfig:
    """Attributes:
      horizon: rollout length (control steps).
      windows: test windows (at most).
      samples: latent samples per stochastic model.
      seed: windows and latents.
    """

    horizon: int = 30
    windows: int = 256
    samples: int = 8
    seed: int = 0


def errors(run: LoadedRun, cfg: HorizonConfig, nfe: int | None = None) -> np.ndarray:
    """Per-sample, per-window, per-horizon RMSE ``[S, N, H]`` on the test split (``S = 1`` for
    deterministic models); ``nfe`` overrides the residual's evaluations per sample."""
    test, train = run.ds.split("test"), run.ds.split("train")
    starts = rollout.windows(test["valid"], cfg.horizon, cfg.windows, cfg.seed)
    scales = rollout.observation_scales(train, run.spec, cfg.horizon)
    keys = jax.random.split(jax.random.key(cfg.seed), cfg.samples if run.model.stochastic else 1)
    model = run.model
    return rollout.rollout_errors(lambda p, q, qd, u, k: model.rollout(p, q, qd, u, k, nfe),
                                  run.params, test, run.spec, cfg.horizon, starts, scales, keys)


def summarise(errs: np.ndarray) -> dict:
    """Numbers of one run from its errors ``[S, N, H]``: diverged windows are counted, not
    averaged (a rollout that leaves the floating-point range has no meaningful RMSE)."""
    finite = np.isfinite(errs).all(-1)  # [S, N]
    per_sample_h = np.array([errs[s][finite[s]].mean(0) if finite[s].any()
                             else np.full(errs.shape[-1], np.nan) for s in range(len(errs))])
    cum = per_sample_h.sum(-1)  # [S]
    # Robust to a few finite but exploding windows (which dominate a mean): the median window.
    med = np.where(finite[..., None], errs, np.nan)
    return {"per_horizon": np.nanmean(per_sample_h, 0).tolist(),
            "per_horizon_median": np.nanmedian(med, (0, 1)).tolist(),
            "cumulative_median": float(np.nanmedian(np.nanmean(med.sum(-1), 0))),
            "per_horizon_sample_std": np.nanstd(per_sample_h, 0).tolist(),
            "cumulative": float(np.nanmean(cum)), "cumulative_sample_std": float(np.nanstd(cum)),
            "diverged": float(1.0 - finite.mean()), "windows": int(errs.shape[1]),
            "samples": int(errs.shape[0])}


def evaluate(run: LoadedRun, cfg: HorizonConfig, cache_dir: pathlib.Path,
             nfe: int | None = None) -> dict:
    """:func:`summarise` of :func:`errors`, cached per run, settings and checkpoint."""
    key = cache_key(run, **dataclasses.asdict(cfg), nfe=nfe, version=_VERSION)
    name = f"{run.path.parent.name}_{run.path.name}_h{cfg.horizon}_nfe{nfe or 'default'}.json"
    result = cached(pathlib.Path(cache_dir) / "horizon" / name, key,
                    lambda: summarise(errors(run, cfg, nfe)))
    return dict(result, model=run.model.name, seed=run.seed, robot=run.robot,
                nfe=(nfe or run.nfe) if run.model.stochastic else None,
                steps_done=run.steps_done)


def from_table(path: str | pathlib.Path) -> tuple[str, dict[str, list[dict]]]:
    """Per-run results read from a Table I file (``stride eval``'s ``table.json``) instead of
    evaluated here: ``(robot, {model: [result per seed]})``. Its state error is this module's
    (both call :func:`~stride_jax.eval.rollout.rollout_errors`); it lacks the median window."""
    path = pathlib.Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no Table I file at {path} (make it with experiments/table1.py)")
    table = json.loads(path.read_text())
    robots = {r["robot"] for r in table["runs"]}
    if len(robots) != 1:
        raise ValueError(f"{path}: expected the runs of one robot, found {sorted(robots)}")
    out: dict[str, list[dict]] = {}
    for r in table["runs"]:
        st = r["state"]
        out.setdefault(r["model"], []).append({
            "per_horizon": st["per_horizon"], "cumulative": st["mean"],
            "cumulative_sample_std": st["spread"], "cumulative_median": None,
            "diverged": st["diverged"], "windows": st["windows"], "model": r["model"],
            "seed": r["seed"], "robot": r["robot"], "nfe": r["nfe"],
            "steps_done": r["steps_done"], "source": str(path)})
    return robots.pop(), out


def over_seeds(results: list[dict]) -> dict:
    """Mean and std over seeds of one model's per-run results."""
    ph = np.array([r["per_horizon"] for r in results], np.float64)  # [seeds, H]
    cum = np.array([r["cumulative"] for r in results], np.float64)
    return {"seeds": [r["seed"] for r in results],
            "per_horizon_mean": np.nanmean(ph, 0).tolist(),
            "per_horizon_std": np.nanstd(ph, 0).tolist(),
            "cumulative_mean": float(np.nanmean(cum)), "cumulative_std": float(np.nanstd(cum)),
            "cumulative_median_mean": (None if any(r["cumulative_median"] is None
                                                   for r in results)
                                       else float(np.mean([r["cumulative_median"]
                                                           for r in results]))),
            "diverged_mean": float(np.mean([r["diverged"] for r in results])),
            "steps_done": sorted({r["steps_done"] for r in results}, key=str)}


LABELS = {"stride": "STRIDE", "delan": "DeLaN + MLP residual", "delan_prior": "DeLaN (prior only)",
          "lnn_diffusion": "LNN + Diffusion", "onn": "ONN (MLP)", "diffusion": "Pure Diffusion"}
COLORS = {"stride": "C3", "delan": "C0", "delan_prior": "C1", "lnn_diffusion": "C2", "onn": "C7",
          "diffusion": "C4"}
