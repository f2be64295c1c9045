"""STRIDE, DeLaN and LNN + Diffusion: a learned Lagrangian prior plus a residual generalised force.

    qdd = M(q)^-1 [tau - C(q, qd) qd - g(q)] + M(q)^-1 eps                  (paper, Eq. 5)

The ``residual`` kind picks how ``eps`` comes about:

* ``"flow"`` (STRIDE): sampled from a conditional flow, ``eps ~ p(eps | q, qd, tau)`` (Sec. III-C);
* ``"diffusion"`` (LNN + Diffusion): sampled from a DDPM of the same size, trained the same way;
* ``"mlp"`` (DeLaN, Lutter et al., 2019, with a deterministic residual): predicted,
  ``eps = r(q, qd, tau)``, by an MLP of the same size;
* ``"none"`` (DeLaN as published: the prior alone, ``eps = 0``), trained on the same
  acceleration loss (the paper's DeLaN baseline, Sec. IV-A: "loss: RMSE on predicted
  accelerations"). Contact forces then have no term of their own: the prior fits what it can.

All are pure functions of a params dict, written for one example. The diffusion baseline models
the residual *force* like STRIDE (the paper words it as a residual acceleration): with everything
else equal, the comparison isolates flow matching against diffusion.

How STRIDE's losses combine (Sec. III-D, Algorithm 1; LNN + Diffusion likewise, with the
denoising loss in place of flow matching). Per example, with
``r* = M(q) qdd - (tau - C qd - g)`` the generalised residual implied by the current prior:

* ``L_acc``, the acceleration error ``|W (qdd - f_LNN - M^-1 eps)|^2``, back-propagated into
  the prior (M, V) but not into the residual. For the generative residuals ``eps`` is the
  residual's **central sample** -- the flow's transport of ``z0 = 0`` (for the DDPM, its
  deterministic DDIM map from ``x = 0``), with ``nfe`` evaluations: a deterministic function of
  the context (the mean for a Gaussian residual, a point between the modes of a symmetric
  mixture). With ``acc_through="mean"`` the residual is a mean head plus a generator of the
  zero-mean remainder (``generative.with_mean``): the acceleration loss trains the head (DeLaN's
  deterministic residual, in effect) and the generator models only the spread around it, so the
  mean prediction cannot drift with the flow. History, both measured: a *random* sample's
  squared error adds the spread ``tr(W M^-1 Cov(eps) M^-T W)``, which the prior lowered by
  inflating M (Go1: the residual left by the prior grew to 10x DeLaN's, foot forces off by
  200 N); the product ``e1 . e2`` of two independent samples' errors removes that term in
  expectation but is unbounded below on a batch, and the prior learned to exploit it (LNN + Diffusion, whose samples spread most: the
  validation loss fell to -1e7 on 2 of 3 Go1 seeds and their rollouts diverged). DeLaN's
  deterministic residual uses the same squared error, trained into both parts;
* ``L_fm``: the conditional flow-matching loss of the flow on the target ``stop_gradient(r*)``
  (the denoising loss for the diffusion residual);
* ``L_res = |(I - P_c) r*|^2``, the size of the residual the prior leaves **outside what the
  stance feet can produce**: ``P_c`` projects onto the range of ``J_c^T``, the transposed sole
  Jacobians of the feet in contact (no rows in free motion and for robots without feet, where
  all of ``r*`` is penalised). Contact forces act only through ``J_c^T f``; what is left (a swing
  leg's joints, a humanoid's arms, a pure torque on the base) holds only what the prior cannot
  express (damping, friction), so the prior is asked to explain the rest;
* ``L = L_acc + fm_weight * L_fm + residual_weight * L_res``.

Why ``L_res``: a residual that sees ``tau`` can cancel any rescaling of the prior (``M -> k M``
with ``eps -> eps + (k - 1) tau + ...`` fits the same accelerations), so without it the split
between prior and residual is not identifiable and drifts (measured: a tiny pendulum STRIDE
learned M = 29 for a unit pendulum and pushed the rest into the flow, blurring its modes). The
penalty asks the prior to explain what it can, the paper's "division of labour" (Sec. III-F).

Why not on the part contacts can produce: penalised everywhere, the residual is shrunk where it
matters most. A quadruped stands on its feet ~90% of the time, and a prior that lowers gravity by
the mean contact force makes ``r*`` smallest -- so it learned exactly that, and the residual's
contact forces were off by their mean (Go1: 60 N error for a 62 N mean normal force, measured).
Why not in free motion only (the first version): a standing or walking humanoid is almost never
airborne, so the penalty hardly ever applied and the prior/residual split drifted (G1, measured:
STRIDE's prior grew a ~140 N m torque on the base that its residual cancelled, and the foot
forces read from the residual were off by 207 N where DeLaN's were off by 37 N). A pure base
force or torque is never in the range of ``J_c^T`` (a foot's force also loads the leg's joints),
so the projection pins the mass and gravity of the prior without biasing the contact part.
Contact flags and Jacobians are used at training time only (simulators, and legged robots' foot
sensors or contact estimators with the robot's kinematic model, give them); the models never take
them as inputs.

Why the stop-gradients: the paper's single objective, taken literally, would regress a *sampled*
residual onto the observed acceleration with a squared error, whose minimiser is the conditional
mean -- exactly the averaging bias the flow is there to avoid (Sec. III-E). Training the flow by
flow matching on the residual the prior leaves keeps it a model of the distribution, while the
prior still learns end to end with the flow's samples in the loop.
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

from stride_jax.dynamics import diffusion, fused, generative, integrate, lagrangian, linalg, mlp
from stride_jax.types import ModelSpec


RESIDUALS = ("mlp", "none") + generative.KINDS
# What the acceleration loss trains besides the prior (module docstring): nothing of the residual
# ("prior", the first version), the residual's central sample ("central", the default), a
# random sample of it ("sample", the paper's Algorithm 1 taken literally), or a mean head beside
# a generator of the zero-mean remainder ("mean", generative.with_mean).
ACC_THROUGH = ("prior", "central", "sample", "mean")


@dataclasses.dataclass(frozen=True)
class StructuredConfig:
    """Sizes and loss settings shared by the structured models (one ``net`` size for every
    network). ``nfe``: evaluations per residual sample; ``integrator``: the flow's ODE solver;
    ``diffusion_*``, ``eta``, ``abar_min``: the diffusion's schedule, parameterisation and
    sampler (``diffusion.DiffusionConfig``); ``acc_through``: what the acceleration loss trains
    (``ACC_THROUGH``, module docstring)."""

    net: mlp.MLPConfig = mlp.MLPConfig()
    diag_floor: float = 1e-3
    nfe: int = 2
    integrator: str = "euler"
    diffusion_steps: int = 100
    eta: float = 0.0
    diffusion_target: str = "v"
    diffusion_clip: float = 5.0
    abar_min: float = 1e-3
    acc_through: str = "central"
    mass_init: float = 1.0  # floating bases: total mass (kg), see LNNConfig
    learn_mass: bool = False
    shared_lnn: bool = False  # one network for L and V (LNNConfig.shared)
    # floating bases: M's translational block m I, V = m g z + V_net, no base position among
    # the prior's inputs (LNNConfig.base_structure); off: a generic Lagrangian (an ablation)
    base_structure: bool = True
    # floating bases with the structure: V_net(orientation, joints) ("net") or gravity's exact
    # multibody form with a learned centre-of-mass offset ("com"; LNNConfig.potential)
    potential: str = "net"
    # floating bases: the networks' context also carries gravity's direction in the base's
    # frame (``gravity_features``), for data whose gravity varies (sloped episodes,
    # ``stride data --slope-deg``): the residual's contact forces, and a next-observation
    # model's whole step, then depend on the slope as the prior's potential does. Off: the
    # paper's context (a model trained on level ground has nothing to learn from it).
    gravity_context: bool = False
    implicit_servo: bool = True  # rollouts: servo PD at the next state (Actuation.implicit)
    fm_weight: float = 1.0
    residual_weight: float = 0.1
    # the one-control-period transition loss (off: the paper's training on accelerations alone;
    # ``models.structured``'s loss, needs ``q_next``, ``qd_next``, ``ctrl`` in the examples)
    transition_weight: float = 0.0
    # the share of each training minibatch the transition term is computed on (its examples are
    # drawn at random, so the term's mean is unbiased; validation takes every example): the term
    # costs ~5x an acceleration step per example, so 0.25 makes a step ~2x instead of ~5x
    transition_fraction: float = 1.0
    # floating bases: the weight of the base's six dofs (their pose change and velocity) in the
    # one-control-period losses, the structured models' transition term and the regressing
    # next-observation model's (ONN's) whole loss, against 1 for each joint: above 1 puts a
    # model's capacity where a velocity-tracking planner's cost reads (the base's motion), not
    # spread over every joint alike. 1: every dof alike, as trained until session 65.
    base_weight: float = 1.0
    # Inference (acceleration, terms, step, rollout): the networks' passes in XLA or as fused
    # kernels (fused.KERNELS; the flow with Euler steps). Training always differentiates in XLA.
    kernel: str = "xla"

    def __post_init__(self):
        fused.kernel_dtype(self.kernel)  # a clear error for an unknown choice
        lagrangian.check_diag_floor(self.diag_floor)
        lagrangian.check_base_structure(self.base_structure, self.learn_mass)
        lagrangian.check_potential(self.potential, self.shared_lnn, self.base_structure)
        if fused.fused(self.kernel) and self.net.activation != "silu":
            raise ValueError(f"kernel {self.kernel!r} implements SiLU networks only, not "
                             f"{self.net.activation!r}; use kernel='xla'")
        if not self.transition_weight >= 0:
            raise ValueError(f"transition_weight must be >= 0, got {self.transition_weight!r}")
        if not 0 < self.transition_fraction <= 1:
            raise ValueError(f"transition_fraction must be in (0, 1], got "
                             f"{self.transition_fraction!r}")
        if self.transition_fraction < 1 and not self.transition_weight:
            raise ValueError(f"transition_fraction {self.transition_fraction!r} needs a "
                             "transition_weight above 0 (it is the share of each minibatch the "
                             "transition term is computed on)")
        if not (math.isfinite(self.base_weight) and self.base_weight > 0):
            raise ValueError(f"base_weight must be a finite number above 0, got {self.base_weight!r}")
        if self.acc_through not in ACC_THROUGH:
            raise ValueError(f"acc_through {self.acc_through!r} is not one of {ACC_THROUGH}")
        self.diffusion  # likewise for the diffusion's settings

    @property
    def inference_net(self) -> mlp.MLPConfig:
        """``net`` with the products ``kernel`` imposes (``xla-bf16``: bfloat16): what every
        network runs as; the parameters are ``net``'s either way."""
        products = fused.products(self.kernel)
        return self.net if products in (None, self.net.products) else dataclasses.replace(
            self.net, products=products)

    @property
    def lnn(self) -> lagrangian.LNNConfig:
        return lagrangian.LNNConfig(net=self.inference_net, diag_floor=self.diag_floor,
                                    mass_init=self.mass_init, learn_mass=self.learn_mass,
                                    shared=self.shared_lnn, base_structure=self.base_structure,
                                    potential=self.potential)

    @property
    def diffusion(self) -> diffusion.DiffusionConfig:
        return diffusion.DiffusionConfig(net=self.inference_net, steps=self.diffusion_steps, eta=self.eta,
                                         clip=self.diffusion_clip, target=self.diffusion_target,
                                         abar_min=self.abar_min)

    def generator(self, kind: str) -> generative.Generator:
        gen = generative.make(kind, self.inference_net, self.nfe, self.integrator, self.kernel,
                              self.diffusion)
        return generative.with_mean(gen, self.inference_net) if self.acc_through == "mean" else gen


class Scales(NamedTuple):
    """Per-dof normalisers ``[nv]`` (dataset standard deviations); ones leave units as they are.

    Networks see ``qd / qd`` and ``tau / tau``; the residual networks output forces in units of
    ``force``; the acceleration loss weighs errors by ``1 / qdd``.
    """

    qd: jax.Array | float = 1.0
    tau: jax.Array | float = 1.0
    force: jax.Array | float = 1.0
    qdd: jax.Array | float = 1.0
    # Next-observation models (ONN, pure diffusion): one-step configuration and velocity
    # changes, commands.
    dq: jax.Array | float = 1.0
    dqd: jax.Array | float = 1.0
    ctrl: jax.Array | float = 1.0


def dof_weights(spec: ModelSpec, cfg: StructuredConfig) -> jax.Array:
    """The per-dof weights ``[nv]`` of the one-control-period losses: ``cfg.base_weight`` on a
    floating base's six dofs, 1 on every joint; a ``base_weight`` other than 1 on a model without
    a floating base is an error naming it."""
    if cfg.base_weight == 1:
        return jnp.ones(spec.nv)
    if not spec.floating_base:
        raise ValueError(f"base_weight {cfg.base_weight!r}: the model has no floating base (the "
                         "weight is that of a floating base's six dofs)")
    return jnp.ones(spec.nv).at[:6].set(cfg.base_weight)


def gravity_features(spec: ModelSpec, q: jax.Array, down: jax.Array | None) -> jax.Array:
    """Gravity's unit direction ``[3]`` in the base's frame, ``R(q)^T down`` (``None``: world
    down, where it is a function of ``q`` alone): what an IMU's accelerometer reads at rest."""
    if not spec.floating_base:
        raise ValueError("gravity_context needs a floating base (a fixed base's gravity is "
                         "its model's, a constant)")
    return integrate.quat_to_mat(q[3:7]).T @ -lagrangian.up_of(down, q.dtype)


def context(spec: ModelSpec, q: jax.Array, qd: jax.Array, tau: jax.Array,
            scales: Scales = Scales(), down: jax.Array | None = None,
            gravity: bool = False) -> jax.Array:
    """The residual's conditioning ``c = (features(q), qd, tau)``, normalised; ``gravity``
    (``StructuredConfig.gravity_context``): and gravity's direction in the base's frame
    (:func:`gravity_features` of ``down``)."""
    parts = [lagrangian.q_features(spec, q), qd / scales.qd, tau / scales.tau]
    if gravity:
        parts.append(gravity_features(spec, q, down))
    return jnp.concatenate(parts)


def _context_dim(spec: ModelSpec, gravity: bool = False) -> int:
    return context(spec, jnp.zeros(spec.nq).at[3].set(1.0) if spec.floating_base
                   else jnp.zeros(spec.nq), jnp.zeros(spec.nv), jnp.zeros(spec.nv),
                   gravity=gravity).shape[0]


def _check(residual: str) -> None:
    if residual not in RESIDUALS:
        raise ValueError(f"unknown residual {residual!r}; available: {', '.join(RESIDUALS)}")


def init(key: jax.Array, spec: ModelSpec, cfg: StructuredConfig, residual: str) -> dict:
    """Parameters ``{'lnn': ..., 'residual': ...}`` with a residual of the given kind."""
    _check(residual)
    key_lnn, key_res = jax.random.split(key)
    c_dim = _context_dim(spec, cfg.gravity_context)
    if residual == "mlp":
        res = mlp.mlp(cfg.net, spec.nv, zero_last=True)[0](key_res, c_dim)
    elif residual == "none":
        res = {}
    else:
        res = cfg.generator(residual).init(key_res, spec.nv, c_dim)
    return {"lnn": lagrangian.lnn_init(key_lnn, spec, cfg.lnn), "residual": res}


def _residual(res_params, spec, cfg, residual, c, key, nfe=None):
    """Normalised residual: a sample (generative kinds; ``key=None``: the central sample) or
    the MLP's prediction."""
    if residual == "mlp":
        return mlp.mlp(cfg.inference_net, spec.nv, zero_last=True)[1](res_params, c)
    if residual == "none":
        return jnp.zeros(spec.nv, c.dtype)
    if key is None:
        return cfg.generator(residual).central(res_params, c, spec.nv, nfe)
    return cfg.generator(residual).sample(res_params, c, key, spec.nv, nfe)


def residual_force(params: dict, spec: ModelSpec, cfg: StructuredConfig, residual: str,
                   q, qd, tau, key, nfe: int | None = None, scales: Scales = Scales(),
                   down: jax.Array | None = None) -> jax.Array:
    """``eps`` [nv]: a sample of the generative residual (``key=None``: its central sample, the
    transport of the latent's centre), or the MLP's (``key`` unused). ``down``: gravity's
    direction, seen by a residual with ``cfg.gravity_context`` (ignored otherwise)."""
    _check(residual)
    c = context(spec, q, qd, tau, scales, down, cfg.gravity_context)
    return scales.force * _residual(params["residual"], spec, cfg, residual, c, key, nfe)


def acceleration(params: dict, spec: ModelSpec, cfg: StructuredConfig, residual: str,
                 q, qd, tau, key, nfe: int | None = None, scales: Scales = Scales(),
                 servo: tuple[jax.Array, jax.Array] | None = None, down: jax.Array | None = None
                 ) -> tuple[jax.Array, jax.Array]:
    """``(qdd [nv], eps [nv])``: predicted acceleration and the generalised residual used.

    ``servo = (tau0, extra)`` integrates the actuators implicitly (``Actuation.implicit``):
    ``(M + diag(extra)) qdd = tau0 - b + eps``; the residual still sees ``tau``. ``down``:
    gravity's direction in the world frame (:func:`lagrangian.potential_energy`; ``None``:
    world -z); a residual with ``cfg.gravity_context`` sees it too, any other is left as it
    was learned.
    """
    M, b = lagrangian.lnn_terms(params["lnn"], spec, q, qd, cfg.lnn, cfg.kernel, down)
    eps = residual_force(params, spec, cfg, residual, q, qd, tau, key, nfe, scales, down)
    if servo is not None:
        tau, extra = servo
        M = M + jnp.diag(extra)
    return linalg.spd_solve(M, tau - b + eps), eps


def terms(params: dict, spec: ModelSpec, cfg: StructuredConfig, residual: str,
          q, qd, tau, key, nfe: int | None = None, scales: Scales = Scales(),
          down: jax.Array | None = None) -> dict:
    """The split ``qdd = prior + residual``: ``{'prior': f_LNN, 'residual': M^-1 eps, 'eps': eps,
    'mass': M}`` (``[nv]``, ``[nv, nv]``), for evaluation and analysis. With the true ``qdd``,
    ``mass @ (qdd - prior)`` is the residual force the prior implies (its inverse dynamics)."""
    M, b = lagrangian.lnn_terms(params["lnn"], spec, q, qd, cfg.lnn, cfg.kernel, down)
    eps = residual_force(params, spec, cfg, residual, q, qd, tau, key, nfe, scales, down)
    return {"prior": linalg.spd_solve(M, tau - b), "residual": linalg.spd_solve(M, eps),
            "eps": eps, "mass": M}


def non_contact_part(force: jax.Array, jac: jax.Array | None) -> jax.Array:
    """``(I - P) force`` [nv]: what of a generalised force ``[nv]`` no forces at the contacts
    can produce, with ``P`` the projection onto the range of ``jac^T`` (``jac [R, nv]``; rows of
    zeros are ignored; ``None`` or no rows: the whole force)."""
    if jac is None or jac.shape[0] == 0:
        return force
    gram = jac @ jac.T
    ridge = 1e-6 * jnp.trace(gram) / gram.shape[0] + 1e-9
    coef = linalg.spd_solve(gram + ridge * jnp.eye(gram.shape[0], dtype=gram.dtype), jac @ force)
    return force - jac.T @ coef


def loss(params: dict, spec: ModelSpec, cfg: StructuredConfig, residual: str,
         q, qd, tau, qdd, key, scales: Scales = Scales(),
         contact_jac: jax.Array | None = None, down: jax.Array | None = None
         ) -> tuple[jax.Array, dict]:
    """One example's training loss and its parts (see the module docstring). ``contact_jac``
    ``[R, nv]``: the sole Jacobians of the feet in contact (rows of zeros for feet in swing;
    ``None`` or no rows: free motion). ``down``: the example's gravity direction (sloped data;
    ``None``: world down), for the prior's potential and a ``gravity_context`` residual."""
    _check(residual)
    cfg = dataclasses.replace(cfg, kernel="xla")  # training differentiates through everything
    key_sample, key_gen = jax.random.split(key)
    M, b = lagrangian.lnn_terms(params["lnn"], spec, q, qd, cfg.lnn, down=down)
    c = context(spec, q, qd, tau, scales, down, cfg.gravity_context)
    generative_kind = residual not in ("mlp", "none")
    if not generative_kind:
        eps = _residual(params["residual"], spec, cfg, residual, c, key_sample)
    else:
        gen = cfg.generator(residual)
        res_params = params["residual"]
        if cfg.acc_through == "prior":
            res_params = jax.lax.stop_gradient(res_params)
        if cfg.acc_through == "sample":
            eps = gen.sample(res_params, c, key_sample, spec.nv)
        elif cfg.acc_through == "mean":
            eps = gen.mean(res_params, c, spec.nv)
        else:
            eps = gen.central(res_params, c, spec.nv)
    # linalg.spd_solve, as inference: on a CPU a vmapped LAPACK factorisation (batched
    # cho_factor) deadlocked the training of a 2-core machine inside jaxlib's ParallelBatchMap
    err = (qdd - linalg.spd_solve(M, tau - b + scales.force * eps)) / scales.qdd
    l_acc = jnp.sum(err ** 2)
    r_star = M @ qdd - (tau - b)  # the residual the prior leaves (N, N m)
    implied = r_star / scales.force
    off_contact = non_contact_part(r_star, contact_jac) / scales.force
    parts = {"acc": l_acc, "res": jnp.sum(implied ** 2), "res_free": jnp.sum(off_contact ** 2)}
    total = l_acc + cfg.residual_weight * parts["res_free"]
    parts["select"] = total  # what the best checkpoint is chosen on: not the generator's loss
    if generative_kind:
        target = jax.lax.stop_gradient(implied)
        l_gen = cfg.generator(residual).loss(params["residual"], target, c, key_gen)
        parts["fm" if residual == "flow" else "ddpm"] = l_gen
        total = total + cfg.fm_weight * l_gen
    return total, parts
