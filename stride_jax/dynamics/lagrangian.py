"""Euler-Lagrange terms by automatic differentiation, exact for floating bases.

For a Lagrangian ``L(q, v) = 1/2 v^T M(q) v - V(q)`` this module returns ``M(q)`` and the bias
force ``b(q, v) = C(q, v) v + g(q)``, so that ``M(q) qdd + b(q, v) = tau + F_ext`` (the paper's
Eq. (3)). No finite differences: every derivative is a JAX ``jvp`` or ``grad``.

Coordinates. Fixed-base robots use hinge angles, whose time derivative is the velocity, and the
textbook equations ``d/dt(dL/dv) - dL/dq = tau``. A floating base follows MuJoCo: world position
with world linear velocity, a quaternion with *body-frame* angular velocity omega. Omega is a
quasi-velocity (not the derivative of any coordinate), so we use the Euler-Poincare / Hamel form

    d/dt (dL/dv) + [0, omega x (dL/domega), 0] - dL/d(delta) = tau,

where ``dL/d(delta)`` is the derivative along ``q (+) delta`` (the retraction of
:mod:`stride_jax.dynamics.integrate`: world translation, body-frame rotation, joint offsets), and
``d/dt (dL/dv) = M qdd + (dM/dt) v`` with ``(dM/dt) v`` the derivative of ``M(q (+) eps v) v`` at
``eps = 0``. World-frame translations commute with everything, so the body rotation's
``omega x p_omega`` is the only structure-constant term. The test suite checks these terms against
MuJoCo's own bias force with MuJoCo's mass matrix and potential plugged in.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from stride_jax.dynamics import mlp
from stride_jax.dynamics.integrate import quat_to_mat, retract
from stride_jax.types import ModelSpec

MassFn = Callable[[jax.Array], jax.Array]  # q [nq] -> M [nv, nv]
PotentialFn = Callable[[jax.Array], jax.Array]  # q [nq] -> V []


def bias_force(mass_fn: MassFn, potential_fn: PotentialFn, q: jax.Array, v: jax.Array,
               floating_base: bool) -> tuple[jax.Array, jax.Array]:
    """Returns ``(M(q) [nv, nv], b(q, v) [nv])`` with ``b = C(q, v) v + g(q)``."""
    nv = v.shape[0]
    move = lambda dv: retract(q, dv, floating_base)
    M = mass_fn(q)
    p = M @ v
    # (dM/dt) v: rate of change of M along the motion, applied to v.
    _, mdot_v = jax.jvp(lambda eps: mass_fn(move(eps * v)) @ v, (jnp.zeros(()),), (jnp.ones(()),))
    # dL/d(delta) at delta = 0, with L = T - V and v held fixed.
    lagrangian = lambda delta: 0.5 * v @ mass_fn(move(delta)) @ v - potential_fn(move(delta))
    dl_dq = jax.grad(lagrangian)(jnp.zeros(nv, v.dtype))
    b = mdot_v - dl_dq
    if floating_base:
        b = b.at[3:6].add(jnp.cross(v[3:6], p[3:6]))
    return M, b


def forward_dynamics(mass_fn: MassFn, potential_fn: PotentialFn, q: jax.Array, v: jax.Array,
                     tau: jax.Array, floating_base: bool) -> jax.Array:
    """``qdd = M(q)^-1 (tau - C(q, v) v - g(q))`` (the paper's f_LNN), by a Cholesky solve."""
    M, b = bias_force(mass_fn, potential_fn, q, v, floating_base)
    return jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(M), tau - b)


# --- The learned prior: Cholesky mass network and scalar potential (the paper's Sec. III-B) ---


@dataclasses.dataclass(frozen=True)
class LNNConfig:
    """Sizes of the two networks and ``diag_floor``: M's eigenvalues stay above it."""

    net: mlp.MLPConfig = mlp.MLPConfig()
    diag_floor: float = 1e-3


def q_features(spec: ModelSpec, q: jax.Array) -> jax.Array:
    """Network input from a configuration: invariant where the physics is.

    Floating base: base height, rotation matrix (9; no quaternion sign ambiguity) and joint
    angles -- not the horizontal position, on which neither M nor V depends. Periodic hinges enter
    as (sin, cos).
    """
    if spec.floating_base:
        joints = q[7:]
        head = [q[2:3], quat_to_mat(q[3:7]).reshape(9)]
    else:
        joints, head = q, []
    if spec.periodic:
        periodic = np.asarray(spec.periodic)  # static mask
        joints = jnp.concatenate([jnp.where(periodic, jnp.sin(joints), joints),
                                  jnp.cos(joints)[periodic]])
    return jnp.concatenate(head + [joints])


def _n_features(spec: ModelSpec) -> int:
    n_hinge = spec.nq - (7 if spec.floating_base else 0)
    return (10 if spec.floating_base else 0) + n_hinge + sum(spec.periodic)


def lnn_init(key: jax.Array, spec: ModelSpec, cfg: LNNConfig = LNNConfig()) -> dict:
    """Parameters of the Cholesky-factor network (nv (nv + 1) / 2 outputs) and of V(q)."""
    key_m, key_v = jax.random.split(key)
    n_tril = spec.nv * (spec.nv + 1) // 2
    init_m, _ = mlp.mlp(cfg.net, n_tril)
    init_v, _ = mlp.mlp(cfg.net, 1)
    return {"mass": init_m(key_m, _n_features(spec)), "potential": init_v(key_v, _n_features(spec))}


def mass_matrix(params: dict, spec: ModelSpec, q: jax.Array,
                cfg: LNNConfig = LNNConfig()) -> jax.Array:
    """``M(q) = L L^T + floor I`` ``[nv, nv]``: L lower triangular with a softplus diagonal.

    The softplus diagonal makes ``L L^T`` positive definite (paper, Sec. III-B); the ``floor I``
    bounds its smallest eigenvalue away from zero, which a positive diagonal alone does not (large
    off-diagonal entries can make ``L L^T`` numerically singular).
    """
    _, apply = mlp.mlp(cfg.net, spec.nv * (spec.nv + 1) // 2)
    raw = apply(params["mass"], q_features(spec, q))
    rows, cols = jnp.tril_indices(spec.nv)
    L = jnp.zeros((spec.nv, spec.nv), raw.dtype).at[rows, cols].set(raw)
    L = L.at[jnp.diag_indices(spec.nv)].set(jax.nn.softplus(jnp.diag(L)))
    return L @ L.T + cfg.diag_floor * jnp.eye(spec.nv, dtype=L.dtype)


def potential_energy(params: dict, spec: ModelSpec, q: jax.Array,
                     cfg: LNNConfig = LNNConfig()) -> jax.Array:
    """Scalar ``V(q)`` (J)."""
    _, apply = mlp.mlp(cfg.net, 1)
    return apply(params["potential"], q_features(spec, q))[0]


def lnn_terms(params: dict, spec: ModelSpec, q: jax.Array, v: jax.Array,
              cfg: LNNConfig = LNNConfig()) -> tuple[jax.Array, jax.Array]:
    """``(M(q), C(q, v) v + g(q))`` of the learned Lagrangian."""
    return bias_force(lambda x: mass_matrix(params, spec, x, cfg),
                      lambda x: potential_energy(params, spec, x, cfg), q, v, spec.floating_base)
