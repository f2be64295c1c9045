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
import math
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from stride_jax.dynamics import fused, linalg, mlp
from stride_jax.dynamics.integrate import quat_between, quat_mul, quat_to_mat, retract
from stride_jax.types import ModelSpec, check_shape

MassFn = Callable[[jax.Array], jax.Array]  # q [nq] -> M [nv, nv]
PotentialFn = Callable[[jax.Array], jax.Array]  # q [nq] -> V []


def bias_force(mass_fn: MassFn, potential_fn: PotentialFn, q: jax.Array, v: jax.Array,
               floating_base: bool) -> tuple[jax.Array, jax.Array]:
    """Returns ``(M(q) [nv, nv], b(q, v) [nv])`` with ``b = C(q, v) v + g(q)``."""
    nv = v.shape[0]
    zero = jnp.zeros(nv, v.dtype)
    # M and V along a displacement delta of q, linearised once at delta = 0: one forward pass of
    # each network, whose stored activations serve both derivatives below (a jvp for dM/dt and
    # a grad for dL/dq would each run the mass network forward again: 6 network passes -> 5).
    (M, _), d_terms = jax.linearize(
        lambda delta: (mass_fn(retract(q, delta, floating_base)),
                       potential_fn(retract(q, delta, floating_base))), zero)
    p = M @ v
    # dM/dt = dM along the motion (delta = dt v); the potential's tangent is dead code.
    mdot_v = d_terms(v)[0] @ v
    # dL/d(delta) at delta = 0 with L = 1/2 v^T M v - V and v held fixed: the transpose of the
    # linear map, applied to the cotangent (1/2 v v^T, -1).
    (dl_dq,) = jax.linear_transpose(d_terms, zero)((0.5 * jnp.outer(v, v),
                                                     -jnp.ones((), v.dtype)))
    b = mdot_v - dl_dq
    if floating_base:
        b = b.at[3:6].add(jnp.cross(v[3:6], p[3:6]))
    return M, b


def forward_dynamics(mass_fn: MassFn, potential_fn: PotentialFn, q: jax.Array, v: jax.Array,
                     tau: jax.Array, floating_base: bool) -> jax.Array:
    """``qdd = M(q)^-1 (tau - C(q, v) v - g(q))`` (the paper's f_LNN), by
    :func:`stride_jax.dynamics.linalg.spd_solve` (a Cholesky solve on a GPU)."""
    M, b = bias_force(mass_fn, potential_fn, q, v, floating_base)
    return linalg.spd_solve(M, tau - b)


# --- The learned prior: Cholesky mass network and scalar potential (the paper's Sec. III-B) ---


@dataclasses.dataclass(frozen=True)
class LNNConfig:
    """Sizes of the two networks and ``diag_floor``: M's eigenvalues stay above it.
    Floating bases: ``gravity`` (m/s^2, along world -z) and ``mass_init``, the robot's total
    mass (kg, a spec-sheet number), held fixed unless ``learn_mass`` (then it is the starting
    value: Adam moves a log-mass only ~lr per step, so a start at 1 kg does not reach a 13 kg
    robot within a training run).

    Why fixed by default (measured, G1, 8000 steps): learned, the mass drifted to 38 kg (STRIDE)
    and 27 kg (DeLaN) from the true 33 kg -- in stance, gravity and the feet's vertical forces
    trade off along directions the data barely constrains -- and the stance forces read from the
    residual carried the difference (~50 N). A team knows its robot's mass to a few percent.

    ``shared``: L's entries and V from one network (shared hidden layers, one more output), as in
    the original DeLaN (Lutter et al., 2019), instead of two. Each pass through the prior is then
    one network pass where it was two: the planner's model step costs less (measured in
    ``results/mppi_latency/README.md``), at the accuracy ``experiments/probes/planning_shared.sh`` measures.

    ``potential`` (floating bases with ``base_structure``): ``"net"`` (the default, as trained
    until session 47), ``V = m g z + V_net(orientation, joints)``; or ``"com"``, gravity's exact
    multibody form ``V = m g e_z . (p + R c(joints)) + s(joints)`` with the centre-of-mass offset
    ``c`` [3] (base frame, m) and a gravity-free joint potential ``s`` (springs) learned from the
    joint angles alone: no extrapolation over orientations, and exact under any gravity
    direction (:func:`potential_energy`'s ``down``; ``V_net`` was fitted on the orientations of
    the data, near upright on level ground). Two networks (not ``shared``).

    ``base_structure`` (floating bases; the default): what rigid-body physics fixes is built in --
    M's translational block is exactly ``m I`` (L's first three rows ``sqrt(m) I``), neither
    network sees the base's position, and ``V = m g z_base + V_net(orientation, joints)``. Off
    (an ablation, :func:`structured_base`): a generic Lagrangian over the floating base's
    coordinates -- every entry of L learned, M and V see the base height besides the orientation
    and joints, and V is the network alone (no mass, no exact gravity term; ``mass_init`` and
    ``learn_mass`` do not apply).
    """

    net: mlp.MLPConfig = mlp.MLPConfig()
    diag_floor: float = 1e-3
    gravity: float = 9.81
    mass_init: float = 1.0
    learn_mass: bool = False
    shared: bool = False
    base_structure: bool = True
    potential: str = "net"

    def __post_init__(self):
        check_diag_floor(self.diag_floor)
        check_base_structure(self.base_structure, self.learn_mass)
        check_potential(self.potential, self.shared, self.base_structure)


POTENTIALS = ("net", "com")


def check_potential(potential: str, shared: bool, base_structure: bool) -> None:
    """``potential`` is one of :data:`POTENTIALS`; ``"com"`` takes two networks and the
    floating-base structure (a fixed base's potential stays ``V_net(joints)``: see
    :func:`check_com`)."""
    if potential not in POTENTIALS:
        raise ValueError(f"potential {potential!r}: use one of {POTENTIALS}")
    if potential == "com" and (shared or not base_structure):
        raise ValueError("potential 'com' (V = m g e_z . (p + R c(joints)) + s(joints)) needs "
                         "two networks (not shared: its network sees the joints alone) and the "
                         "floating-base structure")


def check_com(spec: ModelSpec, cfg: "LNNConfig") -> None:
    """The ``"com"`` potential needs a floating base (it is the base's pose under gravity)."""
    if cfg.potential == "com" and not spec.floating_base:
        raise ValueError("potential 'com' needs a floating base: a fixed base's potential is "
                         "V_net(joints) (potential 'net')")


def check_base_structure(base_structure: bool, learn_mass: bool) -> None:
    """``learn_mass`` needs the floating-base structure: without it there is no total mass."""
    if not base_structure and learn_mass:
        raise ValueError("learn_mass needs base_structure: without the floating-base structure "
                         "(M's translational block m I, V = m g z + V_net) the prior has no total "
                         "mass to learn")


def structured_base(spec: ModelSpec, cfg: LNNConfig) -> bool:
    """Whether the prior has the floating-base structure (``LNNConfig.base_structure`` on a
    floating base): M's translational block ``m I``, ``V = m g z + V_net``, no base position
    among the networks' inputs."""
    return spec.floating_base and cfg.base_structure


def check_diag_floor(floor) -> None:
    """``diag_floor`` must be a finite positive number: M's smallest eigenvalue stays above it."""
    if isinstance(floor, bool) or not isinstance(floor, (int, float)) or not math.isfinite(floor) \
            or floor <= 0:
        raise ValueError(f"diag_floor must be a finite number > 0 (M = L L^T + diag_floor I), "
                         f"got {floor!r}")


def q_features(spec: ModelSpec, q: jax.Array, height: bool = True) -> jax.Array:
    """Network input from a configuration: invariant where the physics is.

    Floating base: base height (unless ``height=False``), rotation matrix (9; no quaternion sign
    ambiguity) and joint angles -- never the horizontal position. Periodic hinges enter as
    (sin, cos).
    """
    check_shape("q_features", "q", q, (spec.nq,), finite=False)  # the callers check values
    if spec.floating_base:
        head = ([q[2:3]] if height else []) + [quat_to_mat(q[3:7]).reshape(9)]
    else:
        head = []
    return jnp.concatenate(head + [joint_features(spec, q)])


def joint_features(spec: ModelSpec, q: jax.Array) -> jax.Array:
    """The joint angles of ``q`` as network input (periodic hinges as sin, cos)."""
    joints = q[7:] if spec.floating_base else q
    if spec.periodic:
        periodic = np.asarray(spec.periodic)  # static mask
        joints = jnp.concatenate([jnp.where(periodic, jnp.sin(joints), joints),
                                  jnp.cos(joints)[periodic]])
    return joints


def _prior_features(spec: ModelSpec, q: jax.Array, cfg: LNNConfig) -> jax.Array:
    """The prior networks' input: :func:`q_features` without the base height where the
    floating-base structure holds (M and V_net do not depend on where the robot is), with it
    where it does not (a generic Lagrangian of the base's coordinates)."""
    return q_features(spec, q, height=not structured_base(spec, cfg))


def _n_features(spec: ModelSpec, cfg: LNNConfig) -> int:
    q0 = jnp.zeros(spec.nq).at[3].set(1.0) if spec.floating_base else jnp.zeros(spec.nq)
    return _prior_features(spec, q0, cfg).shape[0]


def _n_mass_outputs(spec: ModelSpec, cfg: LNNConfig) -> int:
    n = spec.nv * (spec.nv + 1) // 2
    return n - 6 if structured_base(spec, cfg) else n  # the translational block is m I (below)


def lnn_init(key: jax.Array, spec: ModelSpec, cfg: LNNConfig = LNNConfig()) -> dict:
    """Parameters of the Cholesky-factor network and of V(q) (``shared``: of the one network
    with both) and, for a floating base with ``learn_mass``, the log of the total mass."""
    check_com(spec, cfg)
    key_m, key_v = jax.random.split(key)
    n_out, n_in = _n_mass_outputs(spec, cfg), _n_features(spec, cfg)
    if cfg.shared:
        params = {"shared": mlp.mlp(cfg.net, n_out + 1)[0](key_m, n_in)}
    elif cfg.potential == "com":  # c and s from the joints, starting at 0 (mass at the base)
        n_joints = joint_features(spec, jnp.zeros(spec.nq)).shape[0]
        params = {"mass": mlp.mlp(cfg.net, n_out)[0](key_m, n_in),
                  "potential": mlp.mlp(cfg.net, 4, zero_last=True)[0](key_v, n_joints)}
    else:
        params = {"mass": mlp.mlp(cfg.net, n_out)[0](key_m, n_in),
                  "potential": mlp.mlp(cfg.net, 1)[0](key_v, n_in)}
    if structured_base(spec, cfg) and cfg.learn_mass:
        params["log_mass"] = jnp.log(jnp.asarray(cfg.mass_init, jnp.float32))
    return params


def total_mass(params: dict, cfg: LNNConfig) -> jax.Array | float:
    """The floating base's total mass (kg): learned, or ``cfg.mass_init``."""
    return jnp.exp(params["log_mass"]) if cfg.learn_mass else cfg.mass_init


def _factor_layout(spec: ModelSpec, structured: bool) -> tuple[np.ndarray, np.ndarray]:
    """Where L's entries come from (static): ``(index [nv, nv], diag [n_diag])``. ``index``
    points into ``concat([raw, softplus(raw[diag]), [sqrt(m)], [0]])``: the mass network's
    ``n_out`` outputs (learned entries), the softplus of its diagonal outputs, the floating base's
    fixed translational diagonal (``structured``: rows 0-2 of L are ``sqrt(m) I``) and zero
    (above the diagonal)."""
    nv = spec.nv
    rows, cols = np.tril_indices(nv)
    learned = rows >= 3 if structured else np.ones(rows.shape, bool)
    rows, cols = rows[learned], cols[learned]
    n_out = len(rows)
    diag = np.flatnonzero(rows == cols)
    index = np.full((nv, nv), n_out + len(diag) + 1)  # zero
    index[rows, cols] = np.arange(n_out)
    index[rows[diag], cols[diag]] = n_out + np.arange(len(diag))
    if structured:
        index[np.arange(3), np.arange(3)] = n_out + len(diag)
    return index, diag


def mass_matrix(params: dict, spec: ModelSpec, q: jax.Array,
                cfg: LNNConfig = LNNConfig()) -> jax.Array:
    """``M(q) = L L^T + floor I`` ``[nv, nv]``: L lower triangular with a softplus diagonal.

    The softplus diagonal makes ``L L^T`` positive definite (paper, Sec. III-B); the ``floor I``
    bounds its smallest eigenvalue away from zero, which a positive diagonal alone does not (large
    off-diagonal entries can make ``L L^T`` numerically singular).

    Floating base with ``base_structure`` (the default): M does not depend on where the robot is
    (no base position among the inputs), and its translational block is exactly ``m I`` as for
    any rigid multibody with world-frame linear velocity: the first three rows of L are
    ``sqrt(m) I``, the rest is learned. Without it every entry of L is learned from the base
    height, orientation and joints.
    """
    return _mass_from_features(params, spec, _prior_features(spec, q, cfg), cfg)


def _networks(params: dict, spec: ModelSpec, x: jax.Array, cfg: LNNConfig
              ) -> tuple[jax.Array, jax.Array]:
    """``(raw [n_out], V_net [])`` from the input features ``x``: the factor network's outputs
    and the learned part of V."""
    n_out = _n_mass_outputs(spec, cfg)
    if cfg.shared:
        out = mlp.mlp(cfg.net, n_out + 1)[1](params["shared"], x)
        return out[:n_out], out[n_out]
    raw = mlp.mlp(cfg.net, n_out)[1](params["mass"], x)
    if cfg.potential == "com":  # V is not a function of these features (potential_energy)
        return raw, jnp.zeros((), raw.dtype)
    return raw, mlp.mlp(cfg.net, 1)[1](params["potential"], x)[0]


def _factor_from_features(params: dict, spec: ModelSpec, x: jax.Array, cfg: LNNConfig
                          ) -> jax.Array:
    """The Cholesky factor ``L`` ``[nv, nv]`` of :func:`mass_matrix` (without the floor) from
    the network's input features ``x``."""
    if cfg.shared:
        raw = _networks(params, spec, x, cfg)[0]
    else:
        raw = mlp.mlp(cfg.net, _n_mass_outputs(spec, cfg))[1](params["mass"], x)
    return _factor_from_raw(params, spec, raw, cfg)


def _factor_from_raw(params: dict, spec: ModelSpec, raw: jax.Array, cfg: LNNConfig
                     ) -> jax.Array:
    """L from the factor network's outputs ``raw``."""
    structured = structured_base(spec, cfg)
    index, diag = _factor_layout(spec, structured)
    # One gather from the outputs, the softplus of the diagonal ones, sqrt(m) and zero: no
    # scatters, and transcendentals on the diagonal only (a softplus over all of L, masked,
    # cost a CPU planner as much as the mass network itself). The gather takes a flat index and
    # is reshaped: batched by vmap, the [nv, nv] index made XLA's CPU gather a transposed layout
    # and copy it back (Go1, 64 rows: 105 -> 21 us, its gradient 135 -> 84 us; the copies were
    # 8% of a 2-core CPU planning step, results/mppi_latency/cpu_profile/).
    fixed = jnp.sqrt(total_mass(params, cfg)) if structured else 1.0
    entries = jnp.concatenate([raw, jax.nn.softplus(raw[diag]),
                               jnp.asarray([fixed, 0.0], raw.dtype)])
    return entries[index.ravel()].reshape(index.shape)


def _mass_from_features(params: dict, spec: ModelSpec, x: jax.Array, cfg: LNNConfig
                        ) -> jax.Array:
    """:func:`mass_matrix` from the network's input features ``x``."""
    return _mass_from_factor(_factor_from_features(params, spec, x, cfg), cfg)


def _mass_from_factor(L: jax.Array, cfg: LNNConfig) -> jax.Array:
    """``M = L L^T + floor I``."""
    return L @ L.T + cfg.diag_floor * jnp.eye(L.shape[0], dtype=L.dtype)


WORLD_DOWN = (0.0, 0.0, -1.0)


def check_down(spec: ModelSpec, cfg: LNNConfig, down) -> None:
    """A gravity direction needs the floating-base structure: it acts through the base's pose
    in ``V`` (:func:`potential_energy`); a potential learned over a fixed base's joint angles
    (or over the base's raw coordinates) has no frame to turn."""
    if down is None:
        return
    if not structured_base(spec, cfg):
        raise ValueError("a gravity direction (down) needs a floating base with base_structure: "
                         "the learned potential is turned by rotating the base's pose, and this "
                         "prior's potential has no such frame")
    check_direction(down)


def check_direction(down) -> None:
    """``down`` must be ``None`` or a direction ``[3]`` (world frame)."""
    if down is not None and jnp.shape(down) != (3,):
        raise ValueError(f"down must be a direction [3] (world frame), got shape "
                         f"{jnp.shape(down)}")


def up_of(down: jax.Array | None, dtype) -> jax.Array:
    """The unit vector ``[3]`` against gravity: +z, or against ``down`` (any length)."""
    if down is None:
        return -jnp.asarray(WORLD_DOWN, dtype)
    d = jnp.asarray(down, dtype)
    return -d / jnp.linalg.norm(d)


def gravity_frame(q: jax.Array, down: jax.Array) -> jax.Array:
    """``q`` of a floating base with the base's pose rotated into the frame in which ``down``
    (world, any length) points along -z: by the shortest rotation between the two, about the
    world origin (joints unchanged; body-frame velocities are the same in either frame)."""
    r = quat_between(jnp.asarray(down, q.dtype), jnp.asarray(WORLD_DOWN, q.dtype))
    return q.at[:3].set(quat_to_mat(r) @ q[:3]).at[3:7].set(quat_mul(r, q[3:7]))


def potential_energy(params: dict, spec: ModelSpec, q: jax.Array,
                     cfg: LNNConfig = LNNConfig(), down: jax.Array | None = None) -> jax.Array:
    """Scalar ``V(q)`` (J).

    Floating base with ``base_structure``: ``V = m g z_base + V_net(orientation, joints)``, the
    exact form of uniform gravity on a multibody (``g sum_i m_i z_i``, the network holding the
    centre of mass offset), with the same ``m`` as M's translational block. Without this tie the
    prior can fold the mean contact force of standing into a weaker "gravity" and leave the feet
    unloaded. Without the structure: ``V = V_net(height, orientation, joints)``.

    ``down``: the direction of gravity in the world frame ``q`` is expressed in (default world
    -z, as trained). The potential of uniform gravity along ``down`` is the trained one of the
    pose seen from a frame where ``down`` is -z (:func:`gravity_frame`): a model trained on
    level ground then knows the gravity of a world whose frame is not gravity-aligned (a slope
    emulated by tilting gravity under a level floor). Floating base with ``base_structure``
    only (:func:`check_down`). With ``cfg.potential == "com"`` the potential is gravity's
    multibody form (:class:`LNNConfig`), which needs no turn: exact along any ``down``.
    """
    check_down(spec, cfg, down)
    if cfg.potential == "com":
        return _com_potential(params, spec, q, cfg, down)
    if down is not None:
        q = gravity_frame(q, down)
    x = _prior_features(spec, q, cfg)
    if cfg.shared:
        v = _networks(params, spec, x, cfg)[1]
    else:
        v = mlp.mlp(cfg.net, 1)[1](params["potential"], x)[0]
    if structured_base(spec, cfg):
        v = v + total_mass(params, cfg) * cfg.gravity * q[2]
    return v


def _com_potential(params: dict, spec: ModelSpec, q: jax.Array, cfg: LNNConfig,
                   down: jax.Array | None) -> jax.Array:
    """``m g up . (p + R c(joints)) + s(joints)`` (``up``: against ``down``, default +z): the
    ``"com"`` potential (:class:`LNNConfig`)."""
    out = mlp.mlp(cfg.net, 4, zero_last=True)[1](params["potential"], joint_features(spec, q))
    c, springs = out[:3], out[3]
    com = q[:3] + quat_to_mat(q[3:7]) @ c.astype(q.dtype)
    return total_mass(params, cfg) * cfg.gravity * (up_of(down, q.dtype) @ com) + springs


def gravity(params: dict, spec: ModelSpec, q: jax.Array, cfg: LNNConfig = LNNConfig(),
            down: jax.Array | None = None) -> jax.Array:
    """``g(q) = dV/dq`` ``[nv]`` (N, N m): the generalised gravity force of the learned prior,
    the derivative of :func:`potential_energy` along ``q (+) delta`` at ``delta = 0`` (for a
    floating base, along the world translation and the body-frame rotation); ``down`` as
    there."""
    zero = jnp.zeros(spec.nv, jnp.result_type(q, float))
    return jax.grad(lambda d: potential_energy(params, spec, retract(q, d, spec.floating_base),
                                               cfg, down))(zero)


def lnn_terms(params: dict, spec: ModelSpec, q: jax.Array, v: jax.Array,
              cfg: LNNConfig = LNNConfig(), kernel: str = "xla", down: jax.Array | None = None
              ) -> tuple[jax.Array, jax.Array]:
    """``(M(q), C(q, v) v + g(q))`` of the learned Lagrangian: :func:`bias_force` of
    :func:`mass_matrix` and :func:`potential_energy`, computed in the networks' feature space.

    Only first derivatives along ``q (+) delta`` at ``delta = 0`` enter, so the chain rule
    splits them: ``T = dx/d(delta)`` ``[n_features, nv]``, the Jacobian of the features
    (rotation matrix, joint angles) -- no networks in it -- and the networks' own derivatives
    in ``x``. The networks then run one forward pass, one tangent pass (along ``T v``) and one
    transposed pass, with none of the quaternion arithmetic of the retraction differentiated
    through them. Measured with the products on ``L`` below (Go1, 64 x 3 networks, a batch of
    128 on a 2-core CPU; ``experiments/probes/model_step_time.py``): the model step 3.0 -> 2.1 ms.
    Equal to :func:`bias_force` to rounding (tested).

    ``kernel``: ``"xla"`` (JAX's own differentiation, differentiable again: training uses it)
    or a fused-kernel choice of :data:`fused.KERNELS` for inference: the networks' forward and
    tangent passes as one kernel and the transposed pass as another (on GPUs, under ``vmap``).

    ``down``: gravity's direction in the world frame (:func:`potential_energy`; ``None``: world
    -z, the terms above unchanged). The potential's part of ``b`` then comes from one more
    transposed pass of the potential network, at the pose in the gravity-aligned frame; for the
    ``"com"`` potential always from its own gradient (a network of the joints alone, in XLA).
    """
    check_down(spec, cfg, down)
    fb = spec.floating_base
    zero = jnp.zeros(spec.nv, v.dtype)
    features = lambda delta: _prior_features(spec, retract(q, delta, fb), cfg)
    x0, dx = jax.linearize(features, zero)  # dx(delta) = T delta
    dtype = fused.kernel_dtype(kernel)
    # V's cotangent in the pass below: -1 (its derivative joins the kinetic term's), or 0 where
    # the potential comes apart (the "com" form, or taken at another pose: added after)
    v_cot = 0.0 if down is not None or cfg.potential == "com" else -1.0
    if dtype is None:
        def factor_and_potential(x):
            raw, v_net = _networks(params, spec, x, cfg)
            return _factor_from_raw(params, spec, raw, cfg), v_net

        (L, _), d_terms = jax.linearize(factor_and_potential, x0)
        dL = d_terms(dx(v))[0]  # L's rate of change along the motion
        # dL/dx of 1/2 |L^T v|^2 - V: the transposed linear map at the cotangent (g_L, -1)
        transpose = lambda g_L: jax.linear_transpose(d_terms, x0)(
            (g_L, jnp.full((), v_cot, v.dtype)))[0]
    else:
        L, dL, transpose = _fused_passes(params, spec, cfg, x0, dx(v), dtype, v_cot)
    # With M = L L^T + floor I every derivative is a product with v (no derivative of M is
    # formed: matrix-vector work, where differentiating L L^T costs batched matrix products).
    u = L.T @ v
    M = _mass_from_factor(L, cfg)
    p = L @ u + cfg.diag_floor * v  # M v
    mdot_v = dL @ u + L @ (dL.T @ v)
    dl_dx = transpose(jnp.outer(v, u))  # the cotangent of 1/2 |L^T v|^2 on L is v u^T
    (dl_dq,) = jax.linear_transpose(dx, zero)(dl_dx)  # T^T dl_dx
    b = mdot_v - dl_dq
    if cfg.potential == "com":  # the whole potential's force, its m g term included
        b = b + gravity(params, spec, q, cfg, down).astype(v.dtype)
    elif down is not None:
        b = b + _turned_potential_force(params, spec, cfg, q, down, dtype)
    if structured_base(spec, cfg) and cfg.potential == "net":
        # V's exact gravity term m g z (world z: the first three tangents translate the base),
        # m g (-down) under a gravity direction
        b = b.at[:3].add(total_mass(params, cfg) * cfg.gravity * up_of(down, v.dtype))
    if fb:
        b = b.at[3:6].add(jnp.cross(v[3:6], p[3:6]))
    return M, b


def _turned_potential_force(params: dict, spec: ModelSpec, cfg: LNNConfig, q: jax.Array,
                            down: jax.Array, dtype) -> jax.Array:
    """``dV_net/dq`` ``[nv]`` at the pose in the frame where ``down`` is -z
    (:func:`gravity_frame`), along the same tangents as at ``q`` (world translation, body-frame
    rotation, joints: the rotation that aligns gravity acts on the left of the orientation, so
    a body-frame turn of one is a body-frame turn of the other). ``dtype``: the fused kernels'
    (``None``: XLA)."""
    zero = jnp.zeros(spec.nv, q.dtype)
    qg = gravity_frame(q, down)
    xg, dxg = jax.linearize(lambda delta: _prior_features(spec, retract(qg, delta, True), cfg),
                            zero)
    if dtype is None:
        g_x = jax.grad(lambda x: _networks(params, spec, x, cfg)[1])(xg)
    elif cfg.shared:
        cot = jnp.zeros(_n_mass_outputs(spec, cfg) + 1, xg.dtype).at[-1].set(1.0)
        g_x = fused.vjp(params["shared"], xg, cot, dtype)
    else:
        g_x = fused.vjp(params["potential"], xg, jnp.ones((1,), xg.dtype), dtype)
    return jax.linear_transpose(dxg, zero)(g_x.astype(q.dtype))[0]


def _fused_passes(params: dict, spec: ModelSpec, cfg: LNNConfig, x: jax.Array, t: jax.Array,
                  dtype, v_cot: float = -1.0) -> tuple[jax.Array, jax.Array, Callable]:
    """``(L, dL, transpose)`` of :func:`lnn_terms` by the fused kernels: L and its derivative
    along the features' tangent ``t``, and ``g_L -> d(<g_L, L> + v_cot V)/dx`` (``v_cot`` -1,
    or 0 to leave the potential out)."""
    n_out = _n_mass_outputs(spec, cfg)
    factor = lambda raw: _factor_from_raw(params, spec, raw, cfg)
    if cfg.shared:
        out, out_t = fused.jvp(params["shared"], x, t, dtype)
        raw, raw_t = out[:n_out], out_t[:n_out]
    else:
        raw, raw_t = fused.jvp(params["mass"], x, t, dtype)
    L, dL = jax.jvp(factor, (raw,), (raw_t,))
    factor_vjp = jax.vjp(factor, raw)[1]

    def transpose(g_L):
        (g_raw,) = factor_vjp(g_L)
        cot = jnp.full((1,), v_cot, g_raw.dtype)
        if cfg.shared:
            return fused.vjp(params["shared"], x, jnp.concatenate([g_raw, cot]), dtype)
        g_x = fused.vjp(params["mass"], x, g_raw, dtype)
        return g_x if v_cot == 0 else g_x + fused.vjp(params["potential"], x, cot, dtype)

    return L, dL, transpose


def lnn_terms_reference(params: dict, spec: ModelSpec, q: jax.Array, v: jax.Array,
                        cfg: LNNConfig = LNNConfig(), down: jax.Array | None = None
                        ) -> tuple[jax.Array, jax.Array]:
    """:func:`lnn_terms` by :func:`bias_force` through the retraction (the reference the
    feature-space version is tested against)."""
    return bias_force(lambda x: mass_matrix(params, spec, x, cfg),
                      lambda x: potential_energy(params, spec, x, cfg, down), q, v,
                      spec.floating_base)
