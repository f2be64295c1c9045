"""Configuration updates from velocities, floating-base aware (MuJoCo's coordinate conventions).

Fixed-base robots: q and v are hinge angles and rates, ``q' = q + dt * v``.
Floating-base robots (first joint free): ``q = [p (3, world), quat (4, w x y z), joints]`` and
``v = [p_dot (3, world), omega (3, body frame), joint rates]``; the rotation integrates in the body
frame, ``quat' = quat * exp(dt * omega / 2)``, exactly as ``mj_integratePos`` does.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def quat_mul(a: jax.Array, b: jax.Array) -> jax.Array:
    """Hamilton product of two quaternions (w x y z)."""
    aw, av = a[0], a[1:]
    bw, bv = b[0], b[1:]
    return jnp.concatenate([jnp.array([aw * bw - av @ bv]), aw * bv + bw * av + jnp.cross(av, bv)])


def quat_exp(rotvec: jax.Array) -> jax.Array:
    """Unit quaternion of a rotation vector (rad), smooth at zero (safe under autodiff)."""
    angle2 = rotvec @ rotvec
    small = angle2 < 1e-12
    angle = jnp.sqrt(jnp.where(small, 1.0, angle2))
    half = 0.5 * jnp.where(small, 0.0, angle)
    # sin(a/2)/a -> 1/2 - a^2/48 near zero
    scale = jnp.where(small, 0.5 - angle2 / 48.0, jnp.sin(half) / angle)
    return jnp.concatenate([jnp.array([jnp.cos(half)]), scale * rotvec])


def quat_to_mat(quat: jax.Array) -> jax.Array:
    """Rotation matrix ``[3, 3]`` of a unit quaternion (body to world)."""
    w, x, y, z = quat
    return jnp.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def quat_log(quat: jax.Array) -> jax.Array:
    """Rotation vector (rad) of a unit quaternion; the shorter way round (w >= 0)."""
    quat = jnp.where(quat[0] < 0, -quat, quat)
    s = jnp.linalg.norm(quat[1:])
    angle = 2.0 * jnp.arctan2(s, quat[0])
    small = s < 1e-9
    return jnp.where(small, 2.0 * quat[1:], angle / jnp.where(small, 1.0, s) * quat[1:])


def quat_between(a: jax.Array, b: jax.Array) -> jax.Array:
    """The unit quaternion of the shortest rotation taking direction ``a`` [3] to ``b`` [3]
    (normalised here); for opposite directions, half a turn about an axis normal to ``a``."""
    a = a / jnp.linalg.norm(a)
    b = b / jnp.linalg.norm(b)
    w = 1.0 + a @ b
    axis = jnp.cross(a, b)
    # opposite: any normal of a (x's, or y's where a is along x) turned half a turn
    normal = jnp.cross(a, jnp.where(jnp.abs(a[0]) < 0.9, jnp.array([1.0, 0.0, 0.0], a.dtype),
                                    jnp.array([0.0, 1.0, 0.0], a.dtype)))
    opposite = w < 1e-6
    quat = jnp.where(opposite, jnp.concatenate([jnp.zeros(1, a.dtype), normal]),
                     jnp.concatenate([w[None], axis]))
    return quat / jnp.linalg.norm(quat)


def quat_conj(quat: jax.Array) -> jax.Array:
    return quat * jnp.array([1.0, -1.0, -1.0, -1.0])


def difference(q1: jax.Array, q0: jax.Array, floating_base: bool) -> jax.Array:
    """Tangent vector ``[nv]`` from ``q0`` to ``q1``: ``retract(q0, difference(q1, q0)) == q1``."""
    if not floating_base:
        return q1 - q0
    rot = quat_log(quat_mul(quat_conj(q0[3:7]), q1[3:7]))
    return jnp.concatenate([q1[:3] - q0[:3], rot, q1[7:] - q0[7:]])


def retract(q: jax.Array, dv: jax.Array, floating_base: bool) -> jax.Array:
    """Moves configuration ``q`` [nq] along tangent vector ``dv`` [nv] (a velocity times time)."""
    if not floating_base:
        return q + dv
    quat = quat_mul(q[3:7], quat_exp(dv[3:6]))
    return jnp.concatenate([q[:3] + dv[:3], quat / jnp.linalg.norm(quat), q[7:] + dv[6:]])


def semi_implicit_euler(q: jax.Array, v: jax.Array, qdd: jax.Array, dt: float,
                        floating_base: bool) -> tuple[jax.Array, jax.Array]:
    """One step: ``v' = v + dt * qdd``, then ``q' = retract(q, dt * v')`` (MuJoCo's Euler)."""
    v_next = v + dt * qdd
    return retract(q, dt * v_next, floating_base), v_next


def one_step_changes(split: dict, floating_base: bool) -> tuple[np.ndarray, np.ndarray]:
    """Tangent configuration and velocity changes ``[N, nv]`` between consecutive valid steps of
    a dataset split (``q [E, T, nq]``, ``qd [E, T, nv]``, ``valid [E, T]``): the training
    normalisers' and the rollout error's scales."""
    v = split["valid"][:, :-1] & split["valid"][:, 1:]
    q0, q1 = split["q"][:, :-1][v], split["q"][:, 1:][v]
    dq = np.asarray(jax.vmap(lambda a, b: difference(a, b, floating_base))(q1, q0))
    return dq, split["qd"][:, 1:][v] - split["qd"][:, :-1][v]
