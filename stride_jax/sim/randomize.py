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
          "dof_damping", "dof_frictionloss", "jnt_stiffness", "qpos_spring")


class RandValues(NamedTuple):
    """One episode's hidden parameters (scalars unless noted). For analysis only."""

    friction: jax.Array  # scale of sliding friction
    softness: jax.Array  # scale of the contact time constant
    payload_kg: jax.Array  # mass added to the base body
    damping: jax.Array  # scale of joint damping
    frictionloss: jax.Array  # scale of joint dry friction
    spring_nm: jax.Array  # hidden joint-spring stiffness (N m/rad)
    spring_ref: jax.Array  # its rest angle (rad)
    push_t: jax.Array  # push start (s)
    push_s: jax.Array  # push duration (s)
    push_force: jax.Array  # [3] world-frame push force on the base (N)


def sample(key: jax.Array, r: Randomization, episode_s: float) -> RandValues:
    """Draws one episode's values, uniformly in the ranges of ``r``."""
    ks = jax.random.split(key, 10)
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
        spring_nm=u(ks[5], r.spring_nm),
        spring_ref=jnp.asarray(r.spring_ref) + sign * r.spring_offset,
        push_t=u(ks[7], (0.2 * episode_s, 0.8 * episode_s)),
        push_s=u(ks[7], r.push_s),
        push_force=push * jnp.array([jnp.cos(heading), jnp.sin(heading), 0.0]),
    )


def apply_fields(fields: dict, v: RandValues, base_body: int, xp=jnp) -> dict:
    """Returns the model arrays of :data:`FIELDS` with the episode's values applied."""
    f = dict(fields)
    f["geom_friction"] = fields["geom_friction"] * xp.asarray([1.0, 0.0, 0.0]) * v.friction + (
        fields["geom_friction"] * xp.asarray([0.0, 1.0, 1.0]))
    f["pair_friction"] = fields["pair_friction"] * xp.asarray([1.0, 1.0, 0.0, 0.0, 0.0]) * v.friction + (
        fields["pair_friction"] * xp.asarray([0.0, 0.0, 1.0, 1.0, 1.0]))
    f["geom_solref"] = fields["geom_solref"] * xp.asarray([v.softness, 1.0])
    f["pair_solref"] = fields["pair_solref"] * xp.asarray([v.softness, 1.0])
    f["body_mass"] = fields["body_mass"] + v.payload_kg * (xp.arange(fields["body_mass"].shape[0])
                                                           == base_body)
    f["dof_damping"] = fields["dof_damping"] * v.damping
    f["dof_frictionloss"] = fields["dof_frictionloss"] * v.frictionloss
    # The hidden spring acts on hinge joints only (the free joint's stiffness is left alone).
    has_spring = v.spring_nm > 0
    f["jnt_stiffness"] = fields["jnt_stiffness"] + v.spring_nm * fields["_hinge"]
    f["qpos_spring"] = xp.where(has_spring & (fields["_hinge_qpos"] > 0), v.spring_ref,
                                fields["qpos_spring"])
    return {k: f[k] for k in FIELDS}


def _hinge_masks(m: mujoco.MjModel) -> tuple[np.ndarray, np.ndarray]:
    hinge = (m.jnt_type == mujoco.mjtJoint.mjJNT_HINGE).astype(np.float64)
    hinge_qpos = np.zeros(m.nq)
    hinge_qpos[m.jnt_qposadr[hinge > 0]] = 1.0
    return hinge, hinge_qpos


def nominal_fields(m: mujoco.MjModel) -> dict:
    """The arrays of :data:`FIELDS` of a MuJoCo model, plus the masks ``apply_fields`` needs."""
    fields = {k: np.array(getattr(m, k)) for k in FIELDS}
    fields["_hinge"], fields["_hinge_qpos"] = _hinge_masks(m)
    return fields


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


def push_force(v: RandValues, t: jax.Array) -> jax.Array:
    """World-frame force ``[3]`` on the base at time ``t`` (s): one rectangular push per episode."""
    on = (t >= v.push_t) & (t < v.push_t + v.push_s)
    return jnp.where(on, v.push_force, 0.0)
