"""The physics of a structured model's learned Lagrangian prior, term by term, to compose into
a controller, an estimator or an analysis:

    M(q) qdd + C(q, qd) qd + g(q) = tau + eps                          (paper, Eqs. 3 and 5)

Each function takes a model of :func:`stride_jax.dynamics.make` or
:func:`stride_jax.dynamics.load` (STRIDE, DeLaN, DeLaN's prior, LNN + Diffusion), its params and
**one** example (``q [nq]``, ``qd, qdd, tau [nv]``); batch with ``jax.vmap``. Inputs of the wrong
shape, or called eagerly with NaN or inf values, raise :class:`~stride_jax.types.InputError`
naming the argument (values are not checked under ``jit``). Everything is pure and
differentiable (``jax.grad`` through a rollout for gradient-based control), and runs in the
inputs' precision (float64 with ``jax_enable_x64``; float32 parameters are promoted).

Units are the robot's: N and N m for forces, rad and m for coordinates. ``down``: gravity's
direction in the frame ``q`` is expressed in, where it is not world -z (a floating base with the
base structure: :func:`stride_jax.dynamics.lagrangian.potential_energy`); ``None``: as trained.
"""

from __future__ import annotations

import jax

from stride_jax.dynamics import lagrangian, stride
from stride_jax.dynamics.models import Model
from stride_jax.types import check_shape


def _prior(model: Model, fn: str, q, qd=None, extra=None):
    """``(spec, LNNConfig)`` of a structured model, after checking one example's shapes."""
    if model.residual is None or model.spec is None:
        raise TypeError(f"{fn}: model {model.name!r} has no Lagrangian prior (next-observation "
                        "models predict the next state directly)")
    spec = model.spec
    check_shape(fn, "q", q, (spec.nq,))
    if qd is not None:
        check_shape(fn, "qd", qd, (spec.nv,))
    for name, x in (extra or {}).items():
        check_shape(fn, name, x, (spec.nv,))
    return spec, model.config.lnn


def mass_matrix(model: Model, params: dict, q: jax.Array) -> jax.Array:
    """``M(q)`` ``[nv, nv]``: symmetric positive definite (eigenvalues above ``diag_floor``)."""
    spec, cfg = _prior(model, "mass_matrix", q)
    return lagrangian.mass_matrix(params["lnn"], spec, q, cfg)


def potential_energy(model: Model, params: dict, q: jax.Array, down=None) -> jax.Array:
    """``V(q)`` ``[]`` (J), up to a constant."""
    spec, cfg = _prior(model, "potential_energy", q)
    return lagrangian.potential_energy(params["lnn"], spec, q, cfg, down)


def gravity(model: Model, params: dict, q: jax.Array, down=None) -> jax.Array:
    """``g(q) = dV/dq`` ``[nv]``: the generalised force that holds the robot still at ``q``."""
    spec, cfg = _prior(model, "gravity", q)
    return lagrangian.gravity(params["lnn"], spec, q, cfg, down)


def bias_force(model: Model, params: dict, q: jax.Array, qd: jax.Array, down=None) -> jax.Array:
    """``C(q, qd) qd + g(q)`` ``[nv]``."""
    spec, cfg = _prior(model, "bias_force", q, qd)
    return lagrangian.lnn_terms(params["lnn"], spec, q, qd, cfg, down=down)[1]


def coriolis(model: Model, params: dict, q: jax.Array, qd: jax.Array) -> jax.Array:
    """``C(q, qd) qd`` ``[nv]``: Coriolis and centrifugal forces (zero at rest; gravity's
    direction does not enter)."""
    _prior(model, "coriolis", q, qd)
    return bias_force(model, params, q, qd) - gravity(model, params, q)


def inverse_dynamics(model: Model, params: dict, q: jax.Array, qd: jax.Array, qdd: jax.Array,
                     down=None) -> jax.Array:
    """``tau = M(q) qdd + C(q, qd) qd + g(q)`` ``[nv]``: the prior's generalised force for an
    acceleration. (The residual ``eps`` depends on ``tau`` itself; ``model.terms`` splits a
    prediction into prior and residual.)"""
    spec, cfg = _prior(model, "inverse_dynamics", q, qd, {"qdd": qdd})
    M, b = lagrangian.lnn_terms(params["lnn"], spec, q, qd, cfg, down=down)
    return M @ qdd + b


def forward_dynamics(model: Model, params: dict, q: jax.Array, qd: jax.Array, tau: jax.Array,
                     key: jax.Array | None = None, residual: bool = True, down=None
                     ) -> jax.Array:
    """``qdd`` ``[nv]`` for the generalised force ``tau``: the model's acceleration
    ``M^-1 (tau - C qd - g + eps)``. ``residual=False``: the prior alone (``eps = 0``, the
    inverse of :func:`inverse_dynamics`). A generative residual is sampled with ``key``, or
    is its deterministic central sample when ``key`` is None."""
    spec, _ = _prior(model, "forward_dynamics", q, qd, {"tau": tau})
    cfg = model.config
    kind = model.residual if residual else "none"
    scales = model.scales if model.scales is not None else stride.Scales()
    return stride.acceleration(params, spec, cfg, kind, q, qd, tau, key, None, scales,
                               down=down)[0]


def kinetic_energy(model: Model, params: dict, q: jax.Array, qd: jax.Array) -> jax.Array:
    """``T = 1/2 qd^T M(q) qd`` ``[]`` (J)."""
    _prior(model, "kinetic_energy", q, qd)
    return 0.5 * qd @ mass_matrix(model, params, q) @ qd


__all__ = ["bias_force", "coriolis", "forward_dynamics", "gravity", "inverse_dynamics",
           "kinetic_energy", "mass_matrix", "potential_energy"]
