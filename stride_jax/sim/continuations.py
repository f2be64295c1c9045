"""True continuations: the same start state and commands re-simulated under new draws of a
dataset's hidden randomisation.

A stochastic model predicts a distribution of futures; one logged future is one draw of it. To
judge the distribution, evaluation needs several true futures from the same start state: this
module re-simulates a window's logged commands (open loop, as the models roll them out) from its
logged start state in ``K`` worlds, each with a fresh draw of everything the dataset hid from the
models (ground friction and softness, payload, joint damping and friction, the push, the
pendulum's bump: ``randomize.sample`` with the dataset's own ranges), on MuJoCo's CPU backend.
Pushes are drawn on the episode's timeline, so a window sees one only when the new draw puts it
there, as in the data. Everything is drawn per future, each with a model of its own
(a copy takes under a millisecond since the robots' models carry no visual meshes), and with
ground patches (``patch_m > 0``) a fresh draw of the patches.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from stride_jax.robots import Randomization
from stride_jax.sim import randomize, rollout_cpu
from stride_jax.sim.model import SimModel


class Continuations:
    """``q [N, K, H, nq]``, ``qd [N, K, H, nv]`` after each of the ``H`` commands, and
    ``valid [N, K]`` (the world stayed finite and upright)."""

    def __init__(self, q: np.ndarray, qd: np.ndarray, valid: np.ndarray):
        self.q, self.qd, self.valid = q, qd, valid


def randomization_of(meta: dict) -> Randomization | None:
    """The hidden randomisation a dataset was made with (``None``: none)."""
    r = meta.get("randomization")
    if r is None:
        return None
    fields = {f.name for f in dataclasses.fields(Randomization)}
    return Randomization(**{k: tuple(v) if isinstance(v, list) else v
                            for k, v in r.items() if k in fields})


def simulate(sm: SimModel, r: Randomization | None, q0: np.ndarray, qd0: np.ndarray,
             ctrls: np.ndarray, t0: np.ndarray, episode_s: float, k: int, key: jax.Array,
             nthread: int | None = None, down: np.ndarray | None = None) -> Continuations:
    """``k`` continuations of each of ``N`` windows.

    ``q0 [N, nq]``, ``qd0 [N, nv]``: start states; ``ctrls [N, H, nu]``: the logged commands;
    ``t0 [N]``: the windows' start times in their episodes (s); ``episode_s``: the episodes'
    length (s), over which pushes are drawn. ``r=None``: the nominal model, ``k`` identical
    futures. ``down [N, 3]``: each window's gravity direction on sloped data (the slope is the
    logged world's, not hidden: every continuation keeps its window's), with ``r.slope_deg``.
    """
    n, h = ctrls.shape[:2]
    if r is not None and r.rough:  # new draws of the ground too: the heightfield's model
        from stride_jax.sim import terrain
        sm = terrain.rough_model(sm, r)
    if q0.shape != (n, sm.mj.nq) or qd0.shape != (n, sm.mj.nv) or t0.shape != (n,):
        raise ValueError(f"continuations: q0 {q0.shape}, qd0 {qd0.shape} and t0 {t0.shape} must "
                         f"be [N, nq], [N, nv] and [N] for N = {n} windows")
    rep = lambda a: np.repeat(np.asarray(a, np.float64), k, axis=0)  # world i * k + j
    worlds = [sm.mj] * (n * k)
    disturb = ground = None
    if r is not None:
        draw = jax.jit(jax.vmap(lambda kk: randomize.sample(kk, r, episode_s)))
        rand = jax.tree.map(np.asarray, draw(jax.random.split(key, n * k)))
        if down is not None:
            rand = rand._replace(down=rep(down))
        worlds, ground = rollout_cpu.randomized_worlds(sm, r, rand)
        per_world = jax.jit(jax.vmap(lambda v, t, q: randomize.disturbance(v, r, t, q,
                                                                            sm.mj.nv)))
        start = jnp.asarray(rep(t0), jnp.float32)
        disturb = lambda t, q: per_world(jax.tree.map(jnp.asarray, rand),
                                         start + jnp.asarray(t, jnp.float32),
                                         jnp.asarray(q, jnp.float32))
    u = rep(ctrls)
    policy = lambda step, q, qd: u[:, min(step, h - 1)]
    q, qd, alive = rollout_cpu.states(sm, worlds, rep(q0), rep(qd0), h + 1, policy, disturb,
                                      nthread, ground)
    shape = lambda a: a[:, 1:].reshape(n, k, h, -1)
    return Continuations(shape(q), shape(qd), alive[:, -1].reshape(n, k))
