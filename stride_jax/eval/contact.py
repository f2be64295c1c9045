"""Predicted vs true vertical ground reaction forces per foot (the paper's Go1 and G1 figures).

At held-out states, each structured model's residual ``eps`` (``Model.terms``; one latent sample
each for the generative ones) is mapped to per-foot forces through the contact Jacobians of the
feet the data says are in stance (:func:`stride_jax.eval.forces.foot_forces`, least squares);
the vertical component is compared with the simulator's normal force. Swing feet are zero on
both sides by construction, so errors are taken over stance steps only. Predictions are
one-step (at the true state), as in Table I's force error -- not along an open-loop rollout.

Go1 episodes each use one gait of its library (the dataset's ``explore/gait``: trot, pronk, bound,
pace); G1's use one of stand, weight shift or step in place (``explore/mode``), and the
figure shows stepping (the closest to the paper's walking). Episodes come from the test split;
a gait the test split lacks (small datasets) is taken from the other splits, and the numbers
say which.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from stride_jax.eval import forces
from stride_jax.eval.runs import LoadedRun, valid_steps
from stride_jax.robots import go1
from stride_jax.sim import model as sim_model

G1_MODES = ("stand", "weight shift", "step in place")


@dataclasses.dataclass(frozen=True)
class ContactConfig:
    """Attributes:
      steps: held-out steps per gait for the error numbers (at most).
      window: control steps of the plotted time series.
      skip_s: the plotted window starts this long into its episode (s; past the drop-in).
      samples: latent samples per step of a stochastic residual.
      seed: steps and latents.
    """

    steps: int = 1024
    window: int = 100
    skip_s: float = 0.5
    samples: int = 4
    seed: int = 0


def behaviours(robot: str, arrays: dict) -> tuple[tuple[str, ...], np.ndarray]:
    """``(names, index [E])``: the behaviour (gait, mode) of every episode of a dataset; data
    collected by a walking policy (:mod:`stride_jax.control.walk`) is all ``walk``."""
    if "explore/commands" in arrays:
        return ("walk",), np.zeros(len(arrays["explore/commands"]), int)
    if robot == "go1":
        return go1.GAITS, np.asarray(arrays["explore/gait"])
    if robot == "g1":
        return G1_MODES, np.asarray(arrays["explore/mode"])
    raise ValueError(f"no gait labels for robot {robot!r}")


def predicted_forces(run: LoadedRun, sm: sim_model.SimModel, q, qd, tau, stance,
                     samples: int, key: jax.Array) -> np.ndarray:
    """``[S, N, nfeet]`` vertical force (N) of each stance foot from the model's residual at
    states ``q, qd, tau [N, ...]`` with ``stance [N, nfeet]`` (zero for swing feet)."""
    model = run.model
    s = samples if model.stochastic else 1

    @jax.jit
    def eps_fn(params, q, qd, tau, keys):
        one = lambda q, qd, tau, k: model.terms(params, q, qd, tau, k)["eps"]
        return jax.vmap(lambda k: jax.vmap(one)(q, qd, tau, jax.random.split(k, len(q))))(keys)

    eps = eps_fn(run.params, jnp.asarray(q), jnp.asarray(qd), jnp.asarray(tau),
                 jax.random.split(key, s))
    jac = jnp.asarray(forces.foot_jacobians(sm, q), jnp.float32)
    st = jnp.asarray(stance, jnp.float32)
    f = jax.vmap(lambda e: jax.vmap(forces.foot_forces)(jac, st, e))(eps)  # [S, N, F, k]
    return np.asarray(f[..., 2])


def _episodes_of(split_names, ds, names, labels, b) -> tuple[np.ndarray, str]:
    """Episodes (dataset indices) with behaviour ``b``: the test split's, else any split's."""
    for split in split_names:
        eps = np.asarray(ds.meta["splits"][split])
        mine = eps[labels[eps] == b]
        if len(mine):
            return mine, split
    return np.zeros(0, np.int64), ""


def evaluate(run: LoadedRun, cfg: ContactConfig) -> tuple[dict, dict]:
    """``(numbers, arrays)`` for one run: per behaviour, mean |error| (N) over stance steps per
    foot and overall, the mean true stance force, and one plotted window."""
    if run.model.terms is None:
        raise ValueError(f"{run.model.name} has no residual force")
    ds = run.ds
    sm = sim_model.load(ds.meta["robot"])
    names, labels = behaviours(ds.meta["robot"], ds.arrays)
    feet = ds.meta["feet"]
    key = jax.random.key(cfg.seed)
    numbers, arrays = {"seed": run.seed, "steps_done": run.steps_done, "feet": feet}, {}
    all_err, all_true = [], []
    for b, name in enumerate(names):
        eps_idx, split = _episodes_of(("test", "val", "train"), ds, names, labels, b)
        if not len(eps_idx):
            numbers[name] = None
            continue
        sub = {k: ds.arrays[k][eps_idx] for k in ("valid", "q", "qd", "tau", "foot_contact",
                                                   "foot_force")}
        idx = valid_steps(sub, cfg.steps, cfg.seed)
        pick = lambda k: np.asarray(sub[k][idx[:, 0], idx[:, 1]], np.float32)
        stance = pick("foot_contact") > 0.5
        pred = predicted_forces(run, sm, pick("q"), pick("qd"), pick("tau"), stance,
                                cfg.samples, jax.random.fold_in(key, b))
        true = pick("foot_force")
        err = np.where(stance[None], np.abs(pred - true[None]), np.nan)  # [S, N, F]
        numbers[name] = {
            "split": split, "episodes": len(eps_idx), "steps": len(idx),
            "stance_feet": int(stance.sum()),
            "error": float(np.nanmean(err)),
            "error_sample_spread": float(np.nanmean(err, (1, 2)).std()),
            "per_foot": dict(zip(feet, np.nanmean(err, (0, 1)).tolist())),
            "mean_true_stance_force": float(true[stance].mean()) if stance.any() else None}
        all_err.append(err.reshape(err.shape[0], -1))
        all_true.append(true[stance])
        # The plotted window: the first episode of this behaviour with enough valid steps.
        start = int(round(cfg.skip_s / ds.meta["ctrl_dt"]))
        for e in eps_idx:
            v = ds.arrays["valid"][e]
            if start + cfg.window <= len(v) and v[start:start + cfg.window].all():
                sl = slice(start, start + cfg.window)
                get = lambda k: np.asarray(ds.arrays[k][e, sl], np.float32)
                st = get("foot_contact") > 0.5
                arrays[name] = {
                    "t": np.arange(start, start + cfg.window) * ds.meta["ctrl_dt"],
                    "true": get("foot_force"), "stance": st, "episode": int(e), "split": split,
                    "pred": predicted_forces(run, sm, get("q"), get("qd"), get("tau"), st,
                                             cfg.samples, jax.random.fold_in(key, 100 + b))}
                break
    if all_err:
        err = np.concatenate(all_err, axis=1)
        true = np.concatenate(all_true)
        numbers["overall"] = {"error": float(np.nanmean(err)),
                              "mean_true_stance_force": float(true.mean()),
                              "relative_error": float(np.nanmean(err) / true.mean())}
    return numbers, arrays


def over_seeds(per_seed: list[dict], names: tuple[str, ...]) -> dict:
    """Mean and std over seeds of the error per behaviour and overall."""
    out = {}
    for name in (*names, "overall"):
        vals = [p[name]["error"] for p in per_seed if p.get(name)]
        if vals:
            out[name] = {"mean": float(np.mean(vals)), "std": float(np.std(vals)),
                         "n": len(vals)}
            if name == "overall":
                out[name]["relative_mean"] = float(np.mean(
                    [p[name]["relative_error"] for p in per_seed if p.get(name)]))
    return out
