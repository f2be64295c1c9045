"""The one interface every dynamics model offers, and the registry of models.

A :class:`Model` is a bundle of pure functions over a params pytree (written for one example;
batch with ``vmap``):

* ``init(key) -> params``
* ``loss(params, example, key) -> (scalar, parts)``: ``example`` holds ``q, qd, tau, qdd, ctrl``,
  the next ``q_next, qd_next`` and the training-time ``contact_jac``
  ``[R, nv]`` (Jacobians of the feet in stance)
* ``acceleration(params, q, qd, tau, key) -> qdd``: structured models only
* ``terms(params, q, qd, tau, key) -> {'prior', 'residual', 'eps'}``: structured models only,
  the split of the acceleration into the Lagrangian prior and the residual
* every sampling function takes an optional ``nfe`` (residual or generator evaluations)
* ``step(params, q, qd, ctrl, key, down=None) -> (q', qd')``: one control period from a command,
  with the robot's servo model turning commands into joint torques at every substep, as the
  simulator does; ``down``: gravity's direction in the frame ``q`` is expressed in, for the
  models that can be told it (:func:`takes_gravity`; ``None``: world -z, as trained)
* ``rollout(params, q, qd, ctrls [H, nu], key, latents="step") -> (qs [H, nq], qds [H, nv])``:
  a stochastic model's latents drawn afresh at every control step (``"step"``), once for
  the whole rollout (``"rollout"``), or not at all (``"central"``: the residual's central
  sample, deterministic; :func:`rollout_keys` says why each)

and carries what it was made from (``spec``, ``actuation``, ``config``, ``scales``,
``residual``), so that :func:`stride_jax.dynamics.save` needs nothing else and the physics
functions of :mod:`stride_jax.dynamics.physics` can be called on it.

The training loop, the evaluation, the MPPI planner and a user's controller all use these.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from stride_jax.dynamics import (flow, fused, fused_layout, fused_pallas, fused_step, integrate, lagrangian,
                                  next_obs, stride)
from stride_jax.types import InputError, ModelSpec, check_finite

__all__ = ["Actuation", "DEFAULT_NFE", "InputError", "LATENTS", "MODELS", "Model", "load", "make",
           "check_name", "motors", "next_observation", "rollout_keys", "save_definition", "spec_from_meta",
           "step_key", "structured"]


@dataclasses.dataclass(frozen=True)
class Actuation:
    """How commands become generalised forces (read from a dataset's ``meta.json``).

    Position servos: ``tau_j = clip(kp (ctrl - q_j) - kd qd_j, -fmax, fmax)``; motors (``kp`` is
    None): ``tau_j = ctrl``. ``dof`` maps each actuator to the dof it drives.
    """

    dof: tuple[int, ...]
    kp: tuple[float, ...] | None
    kd: tuple[float, ...] | None
    force_range: tuple[tuple[float, float], ...]
    dt: float  # simulation timestep (s)
    n_substeps: int

    @classmethod
    def from_meta(cls, meta: dict) -> "Actuation":
        """From a dataset's ``meta.json``."""
        return cls.from_dict(dict(dof=meta["act_dof"], kp=meta["kp"], kd=meta["kd"],
                                  force_range=meta["actuator_force_range"], dt=meta["sim_dt"],
                                  n_substeps=meta["n_substeps"]))

    @classmethod
    def from_dict(cls, d: dict) -> "Actuation":
        """From :func:`dataclasses.asdict` output after a JSON round trip (lists for tuples)."""
        return cls(dof=tuple(d["dof"]), kp=_tuple(d["kp"]), kd=_tuple(d["kd"]),
                   force_range=tuple(tuple(r) for r in d["force_range"]), dt=d["dt"],
                   n_substeps=d["n_substeps"])

    def torque(self, q: jax.Array, qd: jax.Array, ctrl: jax.Array, spec: ModelSpec) -> jax.Array:
        """Generalised actuator force ``[nv]`` for command ``ctrl`` ``[nu]`` at state (q, qd)."""
        dof = np.asarray(self.dof)
        if self.kp is None:
            force = ctrl
        else:
            qpos_idx = dof + (1 if spec.floating_base else 0)  # free joint: nq = nv + 1
            force = (jnp.asarray(self.kp) * (ctrl - q[qpos_idx])
                     - jnp.asarray(self.kd) * qd[dof])
        lo, hi = np.asarray(self.force_range).T
        limited = hi > lo  # MuJoCo: an empty range means unlimited
        force = jnp.where(limited, jnp.clip(force, lo, hi), force)
        return jnp.zeros(spec.nv, force.dtype).at[dof].set(force)

    def implicit(self, q: jax.Array, qd: jax.Array, ctrl: jax.Array, spec: ModelSpec
                 ) -> tuple[jax.Array, jax.Array]:
        """The servo evaluated at the *next* state of a semi-implicit Euler step of ``dt``:
        ``tau = tau0 - extra * qdd`` with ``tau0 = kp (ctrl - q - dt qd) - kd qd`` and
        ``extra = kp dt^2 + kd dt`` (per dof), so that ``(M + diag(extra)) qdd = tau0 - ...``.
        Stable for any stiffness, where the explicit servo needs ``dt^2 kp / m`` and
        ``dt kd / m`` below Euler's limits -- which a learned inertia lighter than the real one
        (with its armature) breaks. Saturated servos and motors stay explicit (extra = 0)."""
        explicit = self.torque(q, qd, ctrl, spec)
        if self.kp is None:
            return explicit, jnp.zeros_like(explicit)
        dof = np.asarray(self.dof)
        qpos_idx = dof + (1 if spec.floating_base else 0)
        kp, kd, dt = jnp.asarray(self.kp), jnp.asarray(self.kd), self.dt
        raw = kp * (ctrl - q[qpos_idx]) - kd * qd[dof]
        lo, hi = np.asarray(self.force_range).T
        free = (hi <= lo) | ((raw >= lo) & (raw <= hi))  # not saturated
        tau0 = jnp.where(free, kp * (ctrl - q[qpos_idx] - dt * qd[dof]) - kd * qd[dof],
                         explicit[dof])
        extra = jnp.where(free, kp * dt ** 2 + kd * dt, 0.0)
        zeros = jnp.zeros(spec.nv, explicit.dtype)
        return zeros.at[dof].set(tau0), zeros.at[dof].set(extra)


def spec_from_meta(meta: dict) -> ModelSpec:
    """The model spec from a dataset's ``meta.json`` (or :func:`stride_jax.sim.model.robot_meta`)."""
    nq = meta.get("nq") or len(meta["stats"]["q"]["mean"])
    nv = meta.get("nv") or len(meta["stats"]["qd"]["mean"])
    return ModelSpec(nq=nq, nv=nv, floating_base=meta["floating_base"],
                     periodic=tuple(meta["periodic"]))


def _tuple(x):
    return None if x is None else tuple(x)


def motors(nv: int, dt: float = 0.01, n_substeps: int = 1) -> Actuation:
    """Unlimited torque motors on every dof (``tau = ctrl``): the actuation of a robot known
    only from arrays of ``q, qd, tau, qdd`` (``dt``: the step of ``model.step``, s)."""
    return Actuation(dof=tuple(range(nv)), kp=None, kd=None,
                     force_range=((0.0, 0.0),) * nv, dt=dt, n_substeps=n_substeps)


class Model(NamedTuple):
    """A dynamics model as pure functions (the module docstring lists them); it meets the
    contract :class:`stride_jax.types.Model`."""

    name: str
    stochastic: bool
    init: Callable
    loss: Callable
    acceleration: Callable | None
    step: Callable
    rollout: Callable
    terms: Callable | None = None  # structured models: (params, q, qd, tau, key, nfe) -> dict
    # What the model was made from (``make``'s arguments; ``residual``: structured models' kind).
    spec: ModelSpec | None = None
    actuation: Actuation | None = None
    config: stride.StructuredConfig | None = None
    scales: stride.Scales | None = None
    residual: str | None = None
    # a minibatch's mean loss where it is not the mean of ``loss`` over the examples:
    # (params, examples {name: [B, ...]}, keys [B]) -> (loss [], parts); None: that mean
    batch_loss: Callable | None = None


def takes_gravity(model: Model) -> bool:
    """Whether ``model.step`` takes a gravity direction (``down``): the Lagrangian models of a
    floating base with the base structure, whose potential is the pose's height under gravity
    (:func:`stride_jax.dynamics.lagrangian.potential_energy`), and any model trained with
    ``gravity_context`` (its networks see the direction). A next-observation model trained
    without it learned its world's gravity with everything else and cannot be told another."""
    if model.spec is None or model.config is None:
        return False
    if model.residual is None:
        return model.config.gravity_context
    return lagrangian.structured_base(model.spec, model.config.lnn)


# name -> (family, kind): structured models pair the Lagrangian prior with a residual of ``kind``;
# next-observation models predict the change of observation with an MLP (None) or a generator.
# The names are those of the paper's tables and of saved runs (``model.json``): ``delan`` is the
# Lagrangian prior *plus an MLP residual force* (DeLaN extended with a deterministic residual),
# ``delan_prior`` is DeLaN as published (the prior alone). :data:`DESCRIPTIONS` says so in words.
MODELS = {
    "stride": ("structured", "flow"),
    "delan": ("structured", "mlp"),
    "delan_prior": ("structured", "none"),
    "lnn_diffusion": ("structured", "diffusion"),
    "onn": ("next_obs", None),
    "diffusion": ("next_obs", "diffusion"),
}
DESCRIPTIONS = {
    "stride": "Lagrangian prior + flow-matching residual force (STRIDE)",
    "delan": "Lagrangian prior + MLP residual force (DeLaN with a deterministic residual)",
    "delan_prior": "Lagrangian prior alone (DeLaN as published, Lutter et al. 2019)",
    "lnn_diffusion": "Lagrangian prior + diffusion residual force",
    "onn": "MLP of the next observation (no physics)",
    "diffusion": "diffusion model of the next observation (no physics)",
}
# Residual samples per call when the caller does not choose (``nfe`` of the model config is the
# flow's; diffusion needs more evaluations for comparable samples).
DEFAULT_NFE = {"flow": 2, "diffusion": 10}


LATENTS = ("step", "rollout", "central")


def rollout_keys(key: jax.Array, horizon: int, latents: str = "step") -> jax.Array:
    """The keys ``[horizon]`` of a rollout's control steps.

    ``"step"``: a fresh draw at every step. The residual is learned from single transitions,
    ``p(eps | q, qd, tau)``, and i.i.d. draws treat what it does not know as noise that is new
    at every step, so over a rollout its effect averages out (the spread grows like the square
    root of the horizon). ``"rollout"``: one draw held for the whole rollout, each step mapping
    the same latent ``z`` through the flow at the current state (the same quantile of the
    residual's distribution at every step). That is the other limit: what the model does not
    know persists -- a payload, the ground's friction under the feet, a servo's offset -- as
    hidden parameters of a real robot mostly do, and the spread grows like the horizon.
    ``"central"``: no draw. The model steps with ``key=None``, which a generative residual answers
    with its central sample (the latent's centre ``z = 0`` transported by the flow; the
    diffusion's deterministic sampler from 0): one deterministic rollout, the most typical
    outcome rather than a random one. The keys returned are fresh per step (as ``"step"``) for
    callers that still draw beside it (a planner's error draws); :func:`step_key` is what a
    caller hands the model. Deterministic models ignore the key either way.
    """
    if latents in ("step", "central"):
        return jax.random.split(key, horizon)
    if latents == "rollout":
        return jax.vmap(lambda _: key)(jnp.arange(horizon))
    raise ValueError(f"latents must be one of {LATENTS}, got {latents!r}")


def step_key(key: jax.Array, latents: str) -> jax.Array | None:
    """The key a model's ``step`` gets from a rollout's key ``key`` (:func:`rollout_keys`):
    ``None`` (the residual's central sample) for ``"central"``, ``key`` otherwise."""
    return None if latents == "central" else key


def _check_inputs(name: str, spec: ModelSpec, nu: int, **arrays) -> None:
    """Shape checks (always, at trace time) and finiteness checks (on concrete values only: under
    ``jit`` values are unknown; wrap with ``jax.experimental.checkify`` to check them there)."""
    expected = {"q": (spec.nq,), "qd": (spec.nv,), "tau": (spec.nv,), "ctrl": (nu,)}
    for k, x in arrays.items():
        shape = jnp.shape(x)
        if k == "ctrls":
            ok, want = len(shape) == 2 and shape[1] == nu, f"[H, {nu}]"
        else:
            ok, want = shape == expected[k], expected[k]
        if not ok:
            raise InputError(f"{name}: {k} must have shape {want} (one example; vmap over "
                             f"the batch), got {shape}")
        check_finite(name, k, x)


def structured(name: str, spec: ModelSpec, act: Actuation, cfg: stride.StructuredConfig,
               scales: stride.Scales = stride.Scales(), residual: str | None = None) -> Model:
    """The Lagrangian prior with a residual: STRIDE (flow), DeLaN (mlp), LNN + Diffusion."""
    residual = residual or MODELS[name][1]
    nu = len(act.dof)
    weights = stride.dof_weights(spec, cfg)  # of the transition term's dofs
    if cfg.base_weight != 1 and not cfg.transition_weight:
        raise ValueError(f"{name}: base_weight {cfg.base_weight!r} weighs the transition term's "
                         "base dofs, and there is none: set transition_weight above 0")

    def init(key):
        return stride.init(key, spec, cfg, residual)

    def with_transition(total, parts, nxt):
        """The loss and its parts with the transition term ``nxt`` added at its weight."""
        parts["next"] = nxt
        parts["select"] = parts["select"] + cfg.transition_weight * nxt
        return total + cfg.transition_weight * nxt, parts

    def loss(params, ex, key, transition: bool = True):
        lagrangian.check_down(spec, cfg.lnn, ex.get("down"))  # sloped data: the prior is told
        total, parts = stride.loss(params, spec, cfg, residual, ex["q"], ex["qd"], ex["tau"],
                                   ex["qdd"], key, scales, ex.get("contact_jac"),
                                   ex.get("down"))
        if cfg.transition_weight and transition:
            return with_transition(total, parts, transition_error(params, ex))
        return total, parts

    def batch_loss(params, ex, keys):
        """A minibatch's mean loss with the transition term on ``n = ceil(transition_fraction
        * B)`` of its examples only, evenly spaced (``i * B // n``): a minibatch is drawn at
        random, so they are a random subset and the term's mean is unbiased, and spread over
        the batch they put an equal share in every device's shard when data-parallel training
        splits the batch into contiguous blocks (the first ``n`` would load the first devices
        only)."""
        total, parts = jax.vmap(lambda e, k: loss(params, e, k, transition=False))(ex, keys)
        b = len(keys)
        n = max(1, int(np.ceil(cfg.transition_fraction * b)))
        pick = np.arange(n) * b // n
        nxt = jnp.mean(jax.vmap(lambda e: transition_error(params, e))(
            jax.tree.map(lambda a: a[pick], ex)))
        return with_transition(jnp.mean(total), jax.tree.map(jnp.mean, parts), nxt)

    def substep_in(c: stride.StructuredConfig) -> Callable:
        """One simulation substep under config ``c``: the servo law's torques, the acceleration
        (``key=None``: the residual's central sample), semi-implicit Euler."""
        def substep(params, q, qd, ctrl, key, nfe, down=None):
            tau = act.torque(q, qd, ctrl, spec)
            servo = act.implicit(q, qd, ctrl, spec) if cfg.implicit_servo else None
            qdd = stride.acceleration(params, spec, c, residual, q, qd, tau, key, nfe, scales,
                                      servo, down)[0]
            return integrate.semi_implicit_euler(q, qd, qdd, act.dt, spec.floating_base)
        return substep

    xla_substep = substep_in(cfg)
    train_substep = substep_in(dataclasses.replace(cfg, kernel="xla"))  # training: XLA, f32

    def central_period(substep, params, q, qd, ctrl, nfe=None, down=None):
        """One control period of ``substep`` with the residual's central sample throughout."""
        body = lambda carry, _: (substep(params, *carry, ctrl, None, nfe, down), None)
        return jax.lax.scan(body, (q, qd), None, length=act.n_substeps)[0]

    def transition_error(params, ex):
        """The one-control-period transition loss: the model steps from the example's state
        under its command through its substeps, servo in the loop, with the residual's central
        sample (deterministic, differentiable), and the squared error against the logged next
        state is taken in the one-step changes' units (``scales.dq``, ``scales.dqd``), as the
        next-observation models are trained. The acceleration loss fits ``qacc`` at the
        recorded instants only (the start of each control period, where a new servo target has
        just been applied); this term fits what the rollout integrates over the whole period."""
        q1, qd1 = central_period(train_substep, params, ex["q"], ex["qd"], ex["ctrl"],
                                 down=ex.get("down"))
        dq = integrate.difference(q1, ex["q_next"], spec.floating_base) / scales.dq
        return (jnp.sum(weights * dq ** 2)
                + jnp.sum(weights * ((qd1 - ex["qd_next"]) / scales.dqd) ** 2))

    def acceleration(params, q, qd, tau, key, nfe=None):
        _check_inputs(name, spec, nu, q=q, qd=qd, tau=tau)
        return stride.acceleration(params, spec, cfg, residual, q, qd, tau, key, nfe, scales)[0]

    whole = residual == "flow" and _whole_step_applies(spec, act, cfg)

    def _step(params, q, qd, ctrl, key, nfe, down=None):
        if key is None:  # the residual's central sample at every substep: deterministic (the
            # whole-step kernel draws its latents from keys, so XLA runs this step)
            return central_period(xla_substep, params, q, qd, ctrl, nfe, down)

        def substep(carry, k):
            if whole and down is None:  # the whole-step kernel knows world-down gravity only
                return _fused_substep(xla_substep, spec, act, cfg, scales, params, *carry, ctrl,
                                      k, nfe), None
            return xla_substep(params, *carry, ctrl, k, nfe, down), None

        if act.n_substeps == 1:  # planners integrate at the control period: no loop of one
            return substep((q, qd), key)[0]
        (q, qd), _ = jax.lax.scan(substep, (q, qd), jax.random.split(key, act.n_substeps))
        return q, qd

    def step(params, q, qd, ctrl, key, nfe=None, down=None):
        _check_inputs(name, spec, nu, q=q, qd=qd, ctrl=ctrl)
        lagrangian.check_down(spec, cfg.lnn, down)
        return _step(params, q, qd, ctrl, key, nfe, down)

    def rollout(params, q, qd, ctrls, key, nfe=None, latents="step", down=None):
        _check_inputs(name, spec, nu, q=q, qd=qd, ctrls=ctrls)
        lagrangian.check_down(spec, cfg.lnn, down)

        def body(carry, inp):
            ctrl, k = inp
            nxt = _step(params, *carry, ctrl, step_key(k, latents), nfe, down)
            return nxt, nxt

        _, (qs, qds) = jax.lax.scan(body, (q, qd), (ctrls, rollout_keys(key, len(ctrls), latents)))
        return qs, qds

    def terms(params, q, qd, tau, key, nfe=None, down=None):
        _check_inputs(name, spec, nu, q=q, qd=qd, tau=tau)
        return stride.terms(params, spec, cfg, residual, q, qd, tau, key, nfe, scales, down)

    subset = cfg.transition_weight and cfg.transition_fraction < 1
    return Model(name, residual not in ("mlp", "none"), init, loss, acceleration, step, rollout,
                 terms, spec, act, cfg, scales, residual, batch_loss if subset else None)


def whole_step_fits(nv: int, hidden: int) -> bool:
    """Whether the whole-step kernel of a floating base with ``nv`` dofs and networks ``hidden``
    wide fits a GPU's shared memory: its widest tile is L's padded output slots by the padded
    hidden width (``fused_pallas.MAX_TILE``; Go1 fits up to 256 wide, G1 up to 64). Larger
    models take the per-pass kernels where those fit, XLA elsewhere."""
    entries = fused_layout.Layout.of(nv).entries
    return entries * max(16, 1 << (hidden - 1).bit_length()) <= fused_pallas.MAX_TILE


def _whole_step_applies(spec: ModelSpec, act: Actuation, cfg: stride.StructuredConfig) -> bool:
    """Whether a STRIDE model's substep runs as one kernel (``fused_step``): a ``-step`` kernel
    choice, a floating base without periodic joints, position servos integrated implicitly,
    one network for L and V and Euler flow steps (the planning configuration), no mean head
    (the kernel holds the flow alone), the floating-base structure (the kernel's layout fixes
    L's first rows to ``sqrt(m) I`` and adds ``m g z``; without it the per-pass kernels or XLA
    run the step), the paper's residual context (the kernel builds it; ``gravity_context``
    adds inputs it does not hold) and a size that fits shared memory (:func:`whole_step_fits`)."""
    return (fused.whole_step(cfg.kernel) and spec.floating_base and not any(spec.periodic)
            and cfg.base_structure
            and act.kp is not None and cfg.implicit_servo and cfg.shared_lnn
            and cfg.integrator == "euler" and cfg.acc_through != "mean"
            and not cfg.gravity_context
            and whole_step_fits(spec.nv, cfg.net.hidden))


def _fused_substep(xla_substep: Callable, spec: ModelSpec, act: Actuation,
                   cfg: stride.StructuredConfig, scales: stride.Scales, params: dict, q, qd,
                   ctrl, key, nfe):
    """One substep of STRIDE by :mod:`fused_step`: one kernel under ``vmap`` on a GPU, the XLA
    substep otherwise. The residual's latent is drawn from ``key`` as the flow's sampler draws
    it, so both give the same step."""
    nfe = nfe or cfg.nfe
    ref = lambda params, q, qd, ctrl, key: xla_substep(params, q, qd, ctrl, key, nfe)

    def kernel(params, q, qd, ctrl, keys):
        z = jax.vmap(lambda k: jax.random.normal(k, (spec.nv,)))(keys)
        per_dof = lambda x: jnp.zeros(spec.nv).at[np.asarray(act.dof)].set(jnp.asarray(x))
        lo, hi = np.asarray(act.force_range, np.float32).T
        servo = jnp.stack([per_dof(act.kp), per_dof(act.kd), per_dof(lo), per_dof(hi),
                           per_dof((hi > lo).astype(np.float32)),
                           jnp.broadcast_to(1.0 / jnp.asarray(scales.qd), (spec.nv,)),
                           jnp.broadcast_to(1.0 / jnp.asarray(scales.tau), (spec.nv,))])
        lnn_cfg = cfg.lnn
        mass = lagrangian.total_mass(params["lnn"], lnn_cfg)
        static = fused_step.Static(fused_layout.Layout.of(spec.nv, act.dof), nfe,
                                   flow.FlowConfig().time_features, lnn_cfg.diag_floor, act.dt,
                                   fused.kernel_dtype(cfg.kernel))
        return fused_step.step_batched(
            static, fused._layers(params["lnn"]["shared"]), fused._layers(params["residual"]),
            jnp.sqrt(mass), mass * lnn_cfg.gravity, servo, scales.force, q, qd, ctrl, z)

    cpu = jax.vmap(ref, in_axes=(None, 0, 0, 0, 0))
    return fused._batched(kernel, ref, 2, cpu)(params, q, qd, ctrl, key)


def next_observation(name: str, spec: ModelSpec, act: Actuation, cfg: stride.StructuredConfig,
                     scales: stride.Scales = stride.Scales(), kind: str | None = None) -> Model:
    """ONN (``kind=None``: an MLP) or Pure Diffusion (a generator) of the next observation."""
    kind = kind if kind is not None else MODELS[name][1]
    nu = len(act.dof)
    stride.dof_weights(spec, cfg)  # a base weight needs a floating base
    if kind is not None and cfg.base_weight != 1:
        raise ValueError(f"{name}: base_weight {cfg.base_weight!r} weighs the regressing "
                         f"next-observation model's loss; the {kind} generator's loss is not "
                         "weighted per dof")

    def _step(params, q, qd, ctrl, key, nfe, down=None):
        return next_obs.step(params, spec, cfg, scales, q, qd, ctrl, key, nfe, kind, down)

    def check_down(down):
        if down is not None and not cfg.gravity_context:
            raise ValueError(f"{name} has no gravity input: a next-observation model learned "
                             "its world's gravity with everything else, and cannot be told "
                             "another unless trained with gravity_context (on data whose "
                             "gravity varies)")
        lagrangian.check_direction(down)

    def step(params, q, qd, ctrl, key=None, nfe=None, down=None):
        _check_inputs(name, spec, nu, q=q, qd=qd, ctrl=ctrl)
        check_down(down)
        return _step(params, q, qd, ctrl, key, nfe, down)

    def rollout(params, q, qd, ctrls, key=None, nfe=None, latents="step", down=None):
        _check_inputs(name, spec, nu, q=q, qd=qd, ctrls=ctrls)
        check_down(down)
        keys = rollout_keys(key if key is not None else jax.random.key(0), len(ctrls), latents)

        def body(carry, inp):
            ctrl, k = inp
            nxt = _step(params, *carry, ctrl, step_key(k, latents), nfe, down)
            return nxt, nxt

        _, (qs, qds) = jax.lax.scan(body, (q, qd), (ctrls, keys))
        return qs, qds

    return Model(name, kind is not None,
                 lambda key: next_obs.init(key, spec, cfg, nu, scales, kind),
                 lambda params, ex, key: next_obs.loss(params, spec, cfg, scales, ex, key, kind),
                 None, step, rollout, None, spec, act, cfg, scales, None)


def has_substeps(model: Model) -> bool:
    """Whether ``model`` integrates its accelerations over substeps of a control period (the
    structured models), which :func:`with_substeps` can change; a next-observation model
    predicts the period at once."""
    return not (model.actuation is None or model.config is None
                or MODELS[model.name][0] == "next_obs")


def with_substeps(model: Model, n_substeps: int) -> Model:
    """``model`` integrating each control period in ``n_substeps`` substeps (of ``period /
    n_substeps``) instead of the ``actuation.n_substeps`` it was trained with: the same
    parameters and accelerations, a coarser (or finer) integration of them, e.g. a planner
    that trades model steps for time. Structured models only: a next-observation model predicts
    the period at once."""
    if not has_substeps(model):
        raise ValueError(f"model {model.name!r} predicts the control period at once: it has no "
                         "substeps to change")
    if int(n_substeps) != n_substeps or n_substeps < 1:
        raise ValueError(f"n_substeps={n_substeps}: it must be a whole number >= 1")
    act = model.actuation
    period = act.dt * act.n_substeps
    act = dataclasses.replace(act, dt=period / int(n_substeps), n_substeps=int(n_substeps))
    return make(model.name, model.spec, act, model.config, model.scales)


def check_name(name: str) -> None:
    """A ``ValueError`` listing :data:`MODELS` unless ``name`` is one of them."""
    if name not in MODELS:
        raise ValueError(f"unknown model {name!r}; available: {', '.join(MODELS)}")


def make(name: str, spec: ModelSpec, act: Actuation | None = None,
         cfg: stride.StructuredConfig = stride.StructuredConfig(),
         scales: stride.Scales = stride.Scales()) -> Model:
    """The model called ``name`` (:data:`MODELS`, :data:`DESCRIPTIONS`); a clear error for
    unknown names. ``act=None``: :func:`motors` on every dof."""
    check_name(name)
    if not isinstance(spec, ModelSpec):
        raise TypeError(f"spec must be a ModelSpec, got {type(spec).__name__}")
    if not isinstance(cfg, stride.StructuredConfig):
        raise TypeError(f"cfg must be a StructuredConfig (network sizes: "
                        f"StructuredConfig(net=MLPConfig(hidden, depth))), got "
                        f"{type(cfg).__name__}")
    act = act if act is not None else motors(spec.nv)
    if MODELS[name][0] == "next_obs":
        return next_observation(name, spec, act, cfg, scales)
    return structured(name, spec, act, cfg, scales)
