"""What MPPI scores its candidates by: a candidate's open-loop cost through a dynamics model,
one cost from several residual draws (mean, std or CVaR: the risk-aware planner), the softmax
weights of the costs, and the spread of a step's draws (the predicted model error)."""

from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp

Dynamics = Callable[[jax.Array, jax.Array, jax.Array, jax.Array], tuple[jax.Array, jax.Array]]


RISKS = ("mean", "std", "cvar")


def risk_cost(costs: jax.Array, risk: str = "mean", alpha: float = 0.9,
              weight: float = 1.0) -> jax.Array:
    """One cost from ``costs`` ``[R]`` of a candidate's draws: the mean, ``mean + weight * std``
    or ``CVaR_alpha`` (the mean of the ``max(1, round((1 - alpha) R))`` largest). A non-finite
    draw makes the candidate's cost non-finite (it gets no weight)."""
    if risk == "mean":
        return jnp.mean(costs)
    if risk == "std":
        return jnp.mean(costs) + weight * jnp.std(costs)
    worst = max(1, int(round((1.0 - alpha) * costs.shape[0])))
    return jnp.mean(jax.lax.top_k(costs, worst)[0])


def open_loop_cost(dynamics: Dynamics, running_cost: Callable, value: Callable, q: jax.Array,
                   qd: jax.Array, actions: jax.Array, key: jax.Array, unroll: int | bool = 1
                   ) -> tuple[jax.Array, jax.Array, jax.Array]:
    """``(cost [], qs [H, nq], qds [H, nv])`` of the action sequence ``actions`` ``[H, nu]`` from
    ``(q, qd)``: the running costs summed minus the terminal value, and the states it passes
    (each step's own key: a stochastic model draws its residual per step)."""
    H = actions.shape[0]

    def body(carry, inp):
        q, qd, cost = carry
        u, t, k = inp
        q2, qd2 = dynamics(q, qd, u, k)
        return (q2, qd2, cost + running_cost(q, qd, u, t)), (q2, qd2)

    (q, qd, cost), (qs, qds) = jax.lax.scan(body, (q, qd, jnp.zeros(())),
                                            (actions, jnp.arange(H), jax.random.split(key, H)),
                                            unroll=unroll)
    return cost - value(q, qd), qs, qds


def weights(costs: jax.Array, temperature: float, normalize: bool = True) -> jax.Array:
    """MPPI's weights of ``costs`` ``[K]``: ``softmax(-(c - min c) / temperature)``, the shifted
    costs divided by their RMS over the finite ones first when ``normalize``; a non-finite cost
    gets no weight."""
    costs = jnp.where(jnp.isfinite(costs), costs, jnp.inf)
    finite = jnp.isfinite(costs)
    shifted = costs - jnp.min(costs)
    if normalize:
        spread = jnp.sqrt(jnp.sum(jnp.where(finite, shifted, 0.0) ** 2)
                          / jnp.maximum(finite.sum(), 1))
        shifted = shifted / jnp.maximum(spread, 1e-6)
    return jax.nn.softmax(-shifted / temperature)


def velocity_spread(qs: jax.Array, qds: jax.Array) -> jax.Array:
    """The default ``disagreement`` of ``E`` draws of a step, ``qs [E, nq]``, ``qds [E, nv]``:
    the norm of the per-entry standard deviation of the velocities (the error of one draw
    against their mean, in ``qd``'s units)."""
    return jnp.sqrt(jnp.sum(jnp.var(qds, axis=0)))
