"""Hidden per-episode randomisation: sample values, apply them to a model (MJX or MuJoCo).

The same :func:`apply_fields` edits the model arrays for both backends (``xp`` is ``jax.numpy`` for
MJX, ``numpy`` for ``mujoco.MjModel`` copies), so the two simulate the same randomised worlds.
Derived constants (``body_subtreemass``, ``dof_invweight0`` ...) are deliberately not recomputed
after a payload change, in both backends alike, as MuJoCo Playground does.
"""

from __future__ import annotations

import copy
from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from stride_jax.robots import Randomization

FIELDS = ("geom_friction", "pair_friction", "geom_solref", "pair_solref", "body_mass",
          "dof_damping", "dof_frictionloss")


class RandValues(NamedTuple):
    """One episode's hidden parameters (scalars unless noted). For analysis only."""

    friction: jax.Array  # scale of sliding friction
    softness: jax.Array  # scale of the contact time constant
    payload_kg: jax.Array  # mass added to the base body
    damping: jax.Array  # scale of joint damping
    frictionloss: jax.Array  # scale of joint dry friction
    bump_nm: jax.Array  # signed amplitude of the hidden joint torque bump (N m)
    push_t: jax.Array  # push start (s)
    push_s: jax.Array  # push duration (s)
    push_force: jax.Array  # [3] world-frame push force on the base (N)


def sample(key: jax.Array, r: Randomization, episode_s: float) -> RandValues:
    """Draws one episode's values, uniformly in the ranges of ``r``."""
    ks = jax.random.split(key, 11)
    u = lambda k, rng: jax.random.uniform(k, minval=rng[0], maxval=rng[1])
    sign = jnp.where(jax.random.bernoulli(ks[6]), 1.0, -1.0)
    heading = jax.random.uniform(ks[9], minval=-jnp.pi, maxval=jnp.pi)
    push = u(ks[8], r.push_n)
    return RandValues(
        friction=u(ks[0], r.friction),
        softness=u(ks[1], r.softness),
        payload_kg=u(ks[2], r.payload_kg),
        damping=u(ks[3], r.damping),
        frictionloss=u(ks[4], r.frictionloss),
        bump_nm=sign * u(ks[5], r.bump_nm),
        push_t=u(ks[7], (0.2 * episode_s, 0.8 * episode_s)),
        push_s=u(ks[10], r.push_s),
        push_force=push * jnp.array([jnp.cos(heading), jnp.sin(heading), 0.0]),
    )


def apply_fields(fields: dict, v: RandValues, base_body: int, xp=jnp) -> dict:
    """Returns the model arrays of :data:`FIELDS` with the episode's values applied."""
    f = dict(fields)
    one = xp.ones_like(v.friction)
    # Sliding friction only: geoms hold (slide, spin, roll), pairs (slide1, slide2, spin, roll1, roll2).
    f["geom_friction"] = fields["geom_friction"] * xp.stack([v.friction, one, one])
    f["pair_friction"] = fields["pair_friction"] * xp.stack([v.friction, v.friction, one, one, one])
    f["geom_solref"] = fields["geom_solref"] * xp.asarray([v.softness, 1.0])
    f["pair_solref"] = fields["pair_solref"] * xp.asarray([v.softness, 1.0])
    f["body_mass"] = fields["body_mass"] + v.payload_kg * (xp.arange(fields["body_mass"].shape[0])
                                                           == base_body)
    f["dof_damping"] = fields["dof_damping"] * v.damping
    f["dof_frictionloss"] = fields["dof_frictionloss"] * v.frictionloss
    return f


def nominal_fields(m: mujoco.MjModel) -> dict:
    """The arrays of :data:`FIELDS` of a MuJoCo model."""
    return {k: np.array(getattr(m, k)) for k in FIELDS}


def apply_mjx(mx, fields: dict, v: RandValues, base_body: int):
    """An ``mjx.Model`` with the episode's values; vmap over ``v`` for a batch of worlds."""
    jfields = {k: jnp.asarray(a, dtype=jnp.float32) for k, a in fields.items()}
    return mx.replace(**{k: a.astype(getattr(mx, k).dtype)
                         for k, a in apply_fields(jfields, v, base_body, jnp).items()})


def apply_mujoco(m: mujoco.MjModel, fields: dict, v: RandValues, base_body: int) -> mujoco.MjModel:
    """A randomised copy of ``m`` (``v`` holds one episode's values, as numpy or JAX scalars)."""
    out = copy.copy(m)  # MjModel's copy is a deep copy
    vals = RandValues(*(np.asarray(x, dtype=np.float64) for x in v))
    for k, a in apply_fields(fields, vals, base_body, np).items():
        getattr(out, k)[...] = a
    return out


class Disturbance(NamedTuple):
    """Hidden external forces at one instant."""

    push: jax.Array  # [3] world-frame force on the base body (N)
    qfrc: jax.Array  # [nv] generalised force (qfrc_applied)


def disturbance(v: RandValues, r: Randomization, t: jax.Array, qpos: jax.Array,
                nv: int) -> Disturbance:
    """The episode's hidden external forces at time ``t`` (s) and configuration ``qpos``.

    A push is one rectangular force pulse on the base. The bump is a torque on the first dof of
    a fixed-base robot, a Gaussian in the wrapped angle from ``r.bump_at`` (zero if unused).
    """
    on = (t >= v.push_t) & (t < v.push_t + v.push_s)
    push = jnp.where(on, v.push_force, 0.0)
    angle = jnp.mod(qpos[0] - r.bump_at + jnp.pi, 2 * jnp.pi) - jnp.pi
    bump = v.bump_nm * jnp.exp(-0.5 * (angle / r.bump_width) ** 2)
    return Disturbance(push, jnp.zeros(nv).at[0].set(bump))
