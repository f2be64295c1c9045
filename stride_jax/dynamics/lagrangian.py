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

from typing import Callable

import jax
import jax.numpy as jnp

from stride_jax.dynamics.integrate import retract

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
