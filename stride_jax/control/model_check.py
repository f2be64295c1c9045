"""Where a planner's learned model leads it astray: its candidates replayed in the simulator.

At a state the planner meets in closed loop, MPPI proposes ``K`` action sequences and weighs them
by the costs its model predicts. Replaying the same sequences through the true dynamics (the
scenario's MJX model) from the same state says what those weights should have been:

* **model error along the candidates** (off the data's distribution where the noise takes them)
  against the error along the policy's own candidates (near the data), per horizon step: the
  base's linear velocity (m/s) and the joint angles (rad);
* **forward bias**: the base's forward velocity (m/s, in the start's heading) the model predicts
  minus the true one, signed, along every candidate and along the plan the model's weights make:
  a model that under-predicts the speed its plans reach makes the planner overshoot the command;
* **cost bias**: the predicted minus the true cost of each candidate (reward units);
* **ranking**: Spearman's rank correlation of predicted and true costs over the candidates, and
  the share of the model's best 10% that are among the truly best 10%;
* **regret**: the true cost of the plan the model's weights make, minus that of the plan the true
  costs' weights make (the same candidates, the same temperature): what the model's errors cost
  the planner, in the task's own units.

Pure functions of one state; ``experiments/planning_diagnosis.py`` batches them over states
with ``vmap`` (the MPPI step itself is a scan over horizon steps, so a batch of states is one
program). :func:`along` reads a few chosen sequences (the plan, a candidate group's weighted
mean) the same way: what the model expects of each against what the simulator does, and the
planner's objective on either (``experiments/plan_bias.py`` records it along closed-loop
episodes).
"""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from stride_jax.control import costs, mppi


def _ranks(x: jax.Array) -> jax.Array:
    return jnp.argsort(jnp.argsort(x)).astype(jnp.float32)


def spearman(a: jax.Array, b: jax.Array) -> jax.Array:
    """Rank correlation of ``a`` and ``b`` ``[K]`` (ties broken by order; 1: same ranking)."""
    ra, rb = _ranks(a), _ranks(b)
    ra, rb = ra - ra.mean(), rb - rb.mean()
    return jnp.sum(ra * rb) / jnp.sqrt(jnp.sum(ra ** 2) * jnp.sum(rb ** 2))


def one_state(model_dynamics: Callable, true_dynamics: Callable, running_cost: Callable,
              value: Callable, candidates: jax.Array, q: jax.Array, qd: jax.Array,
              key: jax.Array, temperature: float, n_joints: int) -> dict:
    """The comparison at one planner state ``(q, qd)`` (the planner's augmented ``q``; its first
    ``7 + n_joints`` entries are the floating base's pose and the joints) for ``candidates``
    ``[K, H, nu]`` (MPPI's ``Info.candidates``)."""
    keys = jax.random.split(key, candidates.shape[0])
    roll = lambda dyn: jax.vmap(lambda a, k: mppi.open_loop_cost(dyn, running_cost, value, q, qd,
                                                                 a, k))(candidates, keys)
    c_model, qs_m, qds_m = roll(model_dynamics)
    c_true, qs_t, qds_t = roll(true_dynamics)
    vel = jnp.linalg.norm(qds_m[..., :3] - qds_t[..., :3], axis=-1)  # [K, H] base velocity
    joints = jnp.sqrt(jnp.mean((qs_m[..., 7:7 + n_joints] - qs_t[..., 7:7 + n_joints]) ** 2, -1))
    heading = _heading(q)
    fwd = lambda qds: qds[..., :2] @ heading  # [..] forward velocity in the start's heading
    w_model, w_true = mppi.weights(c_model, temperature), mppi.weights(c_true, temperature)
    plan = lambda w: jnp.einsum("k,khu->hu", w, candidates)
    along = lambda dyn, a: mppi.open_loop_cost(dyn, running_cost, value, q, qd, a, key)
    _, _, qds_plan_m = along(model_dynamics, plan(w_model))
    c_plan, _, qds_plan_t = along(true_dynamics, plan(w_model))
    K = candidates.shape[0]
    top = max(1, K // 10)
    best_model = jnp.argsort(jnp.where(jnp.isfinite(c_model), c_model, jnp.inf))[:top]
    best_true = jnp.argsort(jnp.where(jnp.isfinite(c_true), c_true, jnp.inf))[:top]
    overlap = jnp.isin(best_model, best_true).mean()
    ok = jnp.isfinite(c_model) & jnp.isfinite(c_true)
    return dict(vel_err=vel, joint_err=joints, fwd_bias=fwd(qds_m) - fwd(qds_t),
                plan_fwd_model=fwd(qds_plan_m), plan_fwd_true=fwd(qds_plan_t),
                cost_model=c_model, cost_true=c_true,
                spearman=spearman(jnp.where(ok, c_model, 1e9), jnp.where(ok, c_true, 1e9)),
                top10_overlap=overlap, regret=c_plan - along(true_dynamics, plan(w_true))[0],
                finite=ok.mean())


def along(model_dynamics: Callable, true_dynamics: Callable, running_cost: Callable,
          value: Callable, signals: Callable, sequences: jax.Array, q_model: jax.Array,
          q_true: jax.Array, qd: jax.Array, key: jax.Array) -> dict:
    """What the model predicts each action sequence of ``sequences`` ``[S, H, nu]`` does from
    one state, against what the simulator does with it: ``track [S, 2, 3]``, the mean over the
    horizon of ``signals(q, qd) -> [3]`` (e.g. the base's forward and lateral velocity and yaw
    rate) along the model's rollout ``[:, 0]`` and the simulator's ``[:, 1]``, ``cost [S, 2]``,
    each rollout's cost (``running_cost`` summed minus the terminal ``value``: the planner's own
    objective, undiscounted, read on either), ``value [S, 2]``, that terminal value alone, and
    ``end_q [S, 2, nq]``, ``end_qd [S, 2, nv]``, the state each rollout ends in.
    ``q_model`` and ``q_true`` are the same state as each side takes it (a planner's augmented
    state carries corrections, such as a disturbance estimate, that only its model applies); one
    key per sequence, the same on both sides."""
    keys = jax.random.split(key, sequences.shape[0])

    def both(a, k):
        c_m, qs_m, qds_m = costs.open_loop_cost(model_dynamics, running_cost, value, q_model, qd,
                                                a, k)
        c_t, qs_t, qds_t = costs.open_loop_cost(true_dynamics, running_cost, value, q_true, qd,
                                                a, k)
        mean = lambda qs, qds: jnp.mean(jax.vmap(signals)(qs, qds), axis=0)
        return (jnp.stack([mean(qs_m, qds_m), mean(qs_t, qds_t)]), jnp.stack([c_m, c_t]),
                jnp.stack([value(qs_m[-1], qds_m[-1]), value(qs_t[-1], qds_t[-1])]),
                jnp.stack([qs_m[-1], qs_t[-1]]), jnp.stack([qds_m[-1], qds_t[-1]]))

    track, cost, end, end_q, end_qd = jax.vmap(both)(sequences, keys)
    return dict(track=track, cost=cost, value=end, end_q=end_q, end_qd=end_qd)


def _heading(q: jax.Array) -> jax.Array:
    """``[2]`` the floating base's heading (unit, world x-y) from its quaternion ``q[3:7]``
    (w, x, y, z): the yaw of the body's x axis."""
    w, x, y, z = q[3], q[4], q[5], q[6]
    yaw = jnp.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return jnp.stack([jnp.cos(yaw), jnp.sin(yaw)])


def summarise(per_state: dict, n_policy: int) -> dict:
    """Means over states (and candidates) of :func:`one_state`'s outputs stacked over states;
    the last ``n_policy`` candidates are the policy's (MPPI puts them last)."""
    a = {k: np.asarray(v) for k, v in per_state.items()}
    K = a["cost_model"].shape[1]
    noise = slice(0, K - n_policy)
    pol = slice(K - n_policy, K) if n_policy else slice(0, 0)
    bias = a["cost_model"] - a["cost_true"]
    fin = np.isfinite(bias)
    out = dict(
        states=int(a["cost_model"].shape[0]), candidates=K, policy_candidates=n_policy,
        vel_err_noise=np.nanmean(a["vel_err"][:, noise], axis=(0, 1)).tolist(),
        fwd_bias_noise=np.nanmean(a["fwd_bias"][:, noise], axis=(0, 1)).tolist(),
        plan_fwd_bias=np.nanmean(a["plan_fwd_model"] - a["plan_fwd_true"], axis=0).tolist(),
        plan_fwd_true=np.nanmean(a["plan_fwd_true"], axis=0).tolist(),
        joint_err_noise=np.nanmean(a["joint_err"][:, noise], axis=(0, 1)).tolist(),
        cost_bias_mean=float(np.mean(bias[fin])) if fin.any() else float("nan"),
        cost_bias_std=float(np.std(bias[fin])) if fin.any() else float("nan"),
        cost_true_spread=float(np.nanmean(np.nanstd(np.where(np.isfinite(a["cost_true"]),
                                                             a["cost_true"], np.nan), 1))),
        spearman=float(np.nanmean(a["spearman"])), top10_overlap=float(a["top10_overlap"].mean()),
        regret=float(np.nanmean(a["regret"])), finite=float(a["finite"].mean()))
    if n_policy:
        out["vel_err_policy"] = np.nanmean(a["vel_err"][:, pol], axis=(0, 1)).tolist()
        out["joint_err_policy"] = np.nanmean(a["joint_err"][:, pol], axis=(0, 1)).tolist()
        out["fwd_bias_policy"] = np.nanmean(a["fwd_bias"][:, pol], axis=(0, 1)).tolist()
        out["cost_bias_policy"] = float(np.nanmean(bias[:, pol]))
        out["cost_bias_noise"] = float(np.nanmean(bias[:, noise]))
    return out
