"""Shared contracts: the shapes of the arrays the library passes around, the protocols its parts
meet (a dynamics model, a conditional generator, a planner, the dynamics a planner rolls out, a
data-collecting explorer), and what a dynamics model needs to know about the robot it models.

Core maths take **one example** (no batch axis); callers batch with ``vmap``. The aliases below
name the per-example shapes: ``nq`` configuration size, ``nv`` velocity size, ``nu`` actuators,
``H`` horizon steps. Units: rad or m (``q``), rad/s or m/s (``qd``), N m or N (``tau``),
the actuator's unit (``ctrl``: a position target for servos, a torque for motors).

The protocols document call signatures; the concrete bundles are NamedTuples of pure functions
(``dynamics.Model``, ``dynamics.generative.Generator``, ``control.mppi.Planner``) or small
classes (the robots' explorers, ``control.walk.PolicyExplorer``). ``tests/test_types.py`` checks
that they conform.
"""

from __future__ import annotations

import dataclasses
from typing import Annotated, Any, NamedTuple, Protocol, runtime_checkable

import jax
import numpy as np

# ----------------------------------------------------------------------------- shaped arrays

Key = Annotated[jax.Array, "PRNG key"]
Params = Any  # a pytree of arrays (a model's or network's parameters)
Q = Annotated[jax.Array, "[nq] generalised positions (free joint: position, quaternion wxyz)"]
Qd = Annotated[jax.Array, "[nv] generalised velocities (free joint: world linear, body angular)"]
Qdd = Annotated[jax.Array, "[nv] generalised accelerations"]
Tau = Annotated[jax.Array, "[nv] generalised forces"]
Ctrl = Annotated[jax.Array, "[nu] actuator commands"]
Ctrls = Annotated[jax.Array, "[H, nu] a command sequence"]
Qs = Annotated[jax.Array, "[H, nq] positions after each command"]
Qds = Annotated[jax.Array, "[H, nv] velocities after each command"]
Context = Annotated[jax.Array, "[C] a generator's conditioning input"]
Sample = Annotated[jax.Array, "[dim] one sample of a generator"]
Scalar = Annotated[jax.Array, "[] a scalar"]


class InputError(ValueError):
    """A model or physics function was called with inputs of the wrong shape or with non-finite
    values."""


def check_shape(fn: str, arg: str, x, shape: tuple[int, ...], finite: bool = True) -> None:
    """Raises :class:`InputError` naming ``fn`` and ``arg`` unless ``x`` has ``shape`` (checked
    at trace time: free under ``jit``) and, with ``finite`` and where ``x`` is a concrete value,
    is finite (:func:`check_finite`). Core maths take one example; batches go through ``vmap``.
    """
    got = np.shape(x)
    if got != tuple(shape):
        hint = "; vmap over the batch" if len(got) > len(shape) else ""
        raise InputError(f"{fn}: {arg} must have shape {tuple(shape)} (one example{hint}), "
                         f"got {got}")
    if finite:
        check_finite(fn, arg, x)


def check_finite(fn: str, arg: str, x) -> None:
    """Raises :class:`InputError` naming ``fn`` and ``arg`` where ``x`` is a concrete value
    holding NaN or inf. Under ``jit`` (or ``vmap``, ``grad``) the values are unknown and nothing is
    checked: wrap the call with ``jax.experimental.checkify`` to check them there."""
    if not isinstance(x, jax.core.Tracer) and not np.isfinite(np.asarray(x)).all():
        raise InputError(f"{fn}: {arg} holds NaN or inf values")


@dataclasses.dataclass(frozen=True)
class ModelSpec:
    """Static description of a robot's coordinates for a dynamics model.

    Attributes:
      nq: configuration size (a free joint counts 7: position and quaternion).
      nv: velocity size (a free joint counts 6: world linear, body angular).
      floating_base: whether the first joint is a free joint.
      periodic: per hinge coordinate (after the free joint), whether it wraps around (a
        pendulum's angle) and is therefore fed to networks as (sin, cos).
    """

    nq: int
    nv: int
    floating_base: bool
    periodic: tuple[bool, ...] = ()

    def __post_init__(self):
        n_hinge = self.nq - (7 if self.floating_base else 0)
        if self.floating_base and self.nv != self.nq - 1:
            raise ValueError(f"floating base needs nv = nq - 1, got nq={self.nq}, nv={self.nv}")
        if not self.floating_base and self.nv != self.nq:
            raise ValueError(f"fixed base needs nv = nq, got nq={self.nq}, nv={self.nv}")
        if self.periodic and len(self.periodic) != n_hinge:
            raise ValueError(f"periodic has {len(self.periodic)} entries for {n_hinge} hinges")


class ModelInfo(NamedTuple):
    """Static facts an explorer needs about the compiled model (numpy / Python values only;
    ``stride_jax.sim.model.load`` fills it in)."""

    nq: int
    nv: int
    nu: int
    qpos0: Any  # [nq] nominal qpos (the robot's home pose)
    ctrl_lo: Any  # [nu]
    ctrl_hi: Any  # [nu]
    ctrl_dt: float
    base_body: int  # body id of the floating base (or the moving body for fixed-base robots)


# ----------------------------------------------------------------------------- protocols


@runtime_checkable
class Dynamics(Protocol):
    """What a planner rolls out: one control period from ``(q, qd)`` under ``ctrl``, e.g.
    ``functools.partial(model.step, params)`` (``control.mppi.make``'s ``dynamics``)."""

    def __call__(self, q: Q, qd: Qd, ctrl: Ctrl, key: Key) -> tuple[Q, Qd]: ...


@runtime_checkable
class Acceleration(Protocol):
    """A structured model's ``acceleration``: ``qdd`` under generalised force ``tau``."""

    def __call__(self, params: Params, q: Q, qd: Qd, tau: Tau, key: Key,
                 nfe: int | None = None) -> Qdd: ...


@runtime_checkable
class Model(Protocol):
    """Every dynamics model (``dynamics.make``): pure functions over a params pytree, for one
    example. ``nfe``: residual or generator evaluations per sample (None: the model's own).
    Deterministic models ignore ``key``. ``acceleration`` (and ``terms``) are None for the
    next-observation models (no physics to split)."""

    name: str
    stochastic: bool
    spec: ModelSpec | None
    acceleration: Acceleration | None  # None: next-observation models

    def init(self, key: Key) -> Params:
        """Fresh parameters."""

    def loss(self, params: Params, example: dict, key: Key) -> tuple[Scalar, dict]:
        """Training loss of one example (``q, qd, tau, qdd, ctrl, q_next, qd_next,
        contact_jac``) and its named parts (``select``: the part that picks the best step)."""

    def step(self, params: Params, q: Q, qd: Qd, ctrl: Ctrl, key: Key,
             nfe: int | None = None, down: jax.Array | None = None) -> tuple[Q, Qd]:
        """One control period under command ``ctrl`` (the servo model at every substep);
        ``down``: gravity's direction in ``q``'s frame where the model takes one
        (``dynamics.models.takes_gravity``; ``None``: world -z)."""

    def rollout(self, params: Params, q: Q, qd: Qd, ctrls: Ctrls, key: Key,
                nfe: int | None = None, latents: str = "step") -> tuple[Qs, Qds]:
        """``H`` steps under ``ctrls``; a stochastic model's latents fresh at every step
        (``"step"``) or held for the rollout (``"rollout"``: ``dynamics.models.rollout_keys``)."""


@runtime_checkable
class Generator(Protocol):
    """A conditional sampler ``x ~ p(x | c)`` (flow matching or DDPM,
    ``dynamics.generative.make``)."""

    def init(self, key: Key, dim: int, context_dim: int) -> Params:
        """Parameters for samples ``[dim]`` given contexts ``[context_dim]``."""

    def loss(self, params: Params, x: Sample, context: Context, key: Key) -> Scalar:
        """Training loss of one example."""

    def sample(self, params: Params, context: Context, key: Key, dim: int,
               nfe: int | None = None) -> Sample:
        """A random sample, with ``nfe`` network evaluations."""

    def central(self, params: Params, context: Context, dim: int,
                nfe: int | None = None) -> Sample:
        """The deterministic image of the latent's centre (``z0 = 0``)."""


@runtime_checkable
class Planner(Protocol):
    """A receding-horizon planner (``control.mppi.make``): ``init``/``step`` over an immutable
    state that carries the warm start (the plan ``[H, nu]``) and the key."""

    def init(self, key: Key, plan: Ctrls | None = None) -> Any:
        """The first state; ``plan`` warm-starts it."""

    def step(self, state: Any, q: Q, qd: Qd) -> tuple[Ctrl, Any, Any]:
        """``(action [nu], next state, info)`` at state ``(q, qd)``."""


@runtime_checkable
class Explorer(Protocol):
    """The data-collecting controller: pure JAX, written for one world, vmapped by the caller.

    Everything random is drawn from the episode parameters (``sample``) and ``fold_in(key, step)``,
    so that MJX and the CPU backend issue identical controls from identical states.
    """

    def sample(self, key: Key, info: ModelInfo) -> Any:
        """Episode parameters (a pytree of arrays), including the episode key."""

    def reset(self, params: Any, info: ModelInfo) -> tuple[Q, Qd]:
        """Initial ``(qpos [nq], qvel [nv])`` of the episode."""

    def act(self, params: Any, info: ModelInfo, step: jax.Array, qpos: Q, qvel: Qd) -> Ctrl:
        """Control ``[nu]`` at control step ``step`` from the current state. An explorer whose
        class sets ``senses_gravity = True`` also takes ``gravity=`` (the world's gravity
        direction ``[3]``, as an IMU senses it): on sloped data (``Randomization.slope_deg``)
        the backends pass each world's."""
