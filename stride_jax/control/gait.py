"""Variable gait for a quadruped: continuous gait parameters, contact schedules, and MPPI over them.

A gait is three continuous parameters (Raibert; Siekmann et al. 2021 write the same clock):

* ``freq`` f (Hz): a global clock ``c`` advances by ``f dt`` every control period;
* ``duty`` D in (0, 1): the stance fraction of each leg's cycle;
* ``offsets`` phi ``[4]``: leg i is at phase ``p_i = frac(c + phi_i)``, in stance while ``p_i < D``.

Trot, pronk, bound and pace are points of this space (:data:`NAMED`, the offsets of
``robots.go1.GAIT_PHASES``); nothing in the planner knows their names. :func:`classify` names the
nearest one, invariant to a shift of all offsets (the clock's origin is arbitrary).

For planning (:func:`make_gait_dynamics`), the gait parameters are appended to the action vector,
so MPPI samples them per rollout and per step and optimises them jointly with the joint actions:
the joint targets are a gait reference (a stance sweep proportional to the commanded speed and a
swing lift, as in ``robots.go1.GaitExplorer``) plus the planner's residual. The clock lives in the
planner's augmented state (see :mod:`stride_jax.control.planning`). Offsets are unbounded reals
(only their fractional part matters): averaging 0.95 and 1.05 gives 1.0, where averaging the
wrapped 0.95 and 0.05 would give a wrong 0.5.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from stride_jax.robots import go1 as go1_robot

LEGS = go1_robot.LEGS  # FR, FL, RR, RL
N_GAIT = 6  # gait parameters appended to an action: freq, duty, 4 offsets


class Gait(NamedTuple):
    """Gait parameters (one gait; batch with vmap)."""

    freq: jax.Array  # [] Hz
    duty: jax.Array  # [] stance fraction of the cycle, in (0, 1)
    offsets: jax.Array  # [4] phase offset of each leg (cycles; only the fractional part matters)


def named(name: str, freq: float = 2.0, duty: float = 0.5) -> Gait:
    """Trot, pronk, bound or pace at ``freq`` Hz and stance fraction ``duty``."""
    if name not in go1_robot.GAITS:
        raise ValueError(f"unknown gait {name!r}; named gaits: {', '.join(go1_robot.GAITS)}")
    offsets = go1_robot.GAIT_PHASES[go1_robot.GAITS.index(name)]
    # numpy, not jnp: a module-level table must not start JAX (the XLA flags come later)
    return Gait(np.float32(freq), np.float32(duty), np.asarray(offsets, np.float32))


NAMED = {name: named(name) for name in go1_robot.GAITS}


def leg_phases(clock: jax.Array, offsets: jax.Array) -> jax.Array:
    """Phase of each leg in [0, 1): ``frac(clock + offsets)``; ``[n_legs]``."""
    return jnp.mod(clock + offsets, 1.0)


def in_stance(phases: jax.Array, duty: jax.Array) -> jax.Array:
    """Whether each leg is scheduled on the ground: ``phase < duty``; bool ``[n_legs]``."""
    return phases < duty


def swing_height(phases: jax.Array, duty: jax.Array, height: float | jax.Array) -> jax.Array:
    """Scheduled foot height above its stance height (m): 0 in stance, a half sine of amplitude
    ``height`` through swing; ``[n_legs]``."""
    u = (phases - duty) / jnp.maximum(1.0 - duty, 1e-3)
    return jnp.where(in_stance(phases, duty), 0.0, height * jnp.sin(jnp.pi * jnp.clip(u, 0, 1)))


def schedule(gait: Gait, n_steps: int, dt: float, clock0: float | jax.Array = 0.0) -> jax.Array:
    """Contact schedule of a fixed gait: bool ``[n_steps, n_legs]``, True where a foot is down."""
    clocks = clock0 + gait.freq * dt * jnp.arange(n_steps)
    return jax.vmap(lambda c: in_stance(leg_phases(c, gait.offsets), gait.duty))(clocks)


def _circ(a, b):
    d = jnp.abs(jnp.mod(a - b, 1.0))
    return jnp.minimum(d, 1.0 - d)


def gait_distance(offsets_a: jax.Array, offsets_b: jax.Array) -> jax.Array:
    """Distance between two offset patterns (cycles), minimised over a common shift: the mean
    circular distance of the legs' phases relative to the first leg."""
    rel = lambda o: o - o[0]
    return jnp.mean(_circ(rel(jnp.asarray(offsets_a)), rel(jnp.asarray(offsets_b))))


def classify(offsets) -> tuple[str, float]:
    """The named gait nearest to ``offsets`` ``[4]`` and its distance (0: exactly that gait;
    0.25 is as far as two named gaits are apart)."""
    d = {n: float(gait_distance(offsets, g.offsets)) for n, g in NAMED.items()}
    best = min(d, key=d.get)
    return best, d[best]


# ---------------------------------------------------------------------------------------------
# Gait reference and planning with gait parameters in the action.


@dataclasses.dataclass(frozen=True)
class GaitConfig:
    """The gait reference and the bounds MPPI samples gait parameters in.

    Attributes:
      freq: (lo, hi) gait frequency bounds (Hz).
      duty: (lo, hi) stance fraction bounds.
      offset: (lo, hi) bounds of each unwrapped leg offset (cycles).
      residual: joint-target residual per unit action (rad); the planner's joint actions are in
        [-1, 1].
      lift: knee flexion at mid-swing (rad).
      leg_length: effective thigh-to-foot length (m) turning commanded speed into stride sweep.
      max_sweep: largest thigh sweep amplitude (rad).
      yaw_gain: stride difference between the sides per rad/s of commanded yaw rate (fraction).
    """

    freq: tuple[float, float] = (1.0, 4.0)
    duty: tuple[float, float] = (0.3, 0.8)
    offset: tuple[float, float] = (-1.0, 2.0)
    residual: float = 0.3
    lift: float = 0.6
    leg_length: float = 0.3
    max_sweep: float = 0.4
    yaw_gain: float = 0.3

    def __post_init__(self):
        for name in ("freq", "duty", "offset"):
            lo, hi = getattr(self, name)
            if not hi > lo:
                raise ValueError(f"GaitConfig.{name}: upper bound {hi} must exceed {lo}")
        if not (0 < self.duty[0] and self.duty[1] < 1):
            raise ValueError(f"GaitConfig.duty must lie inside (0, 1), got {self.duty}")
        if self.freq[0] <= 0:
            raise ValueError(f"GaitConfig.freq must be positive, got {self.freq}")

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Bounds of the gait part of the action: ``[freq, duty, offset x 4]``, two ``[6]``."""
        lo = np.array([self.freq[0], self.duty[0]] + [self.offset[0]] * 4, np.float32)
        hi = np.array([self.freq[1], self.duty[1]] + [self.offset[1]] * 4, np.float32)
        return lo, hi


def split_action(u: jax.Array, nu: int) -> tuple[jax.Array, Gait]:
    """A planner action ``[nu + 6]`` -> (joint actions ``[nu]``, :class:`Gait`)."""
    if u.shape[-1] != nu + N_GAIT:
        raise ValueError(f"a gait action has {nu} joint entries and {N_GAIT} gait parameters, "
                         f"got {u.shape[-1]} entries")
    return u[:nu], Gait(u[nu], u[nu + 1], u[nu + 2:nu + 6])


def join_action(joint: jax.Array, gait: Gait) -> jax.Array:
    """Inverse of :func:`split_action`."""
    return jnp.concatenate([joint, jnp.stack([gait.freq, gait.duty]), gait.offsets])


def reference(cfg: GaitConfig, gait: Gait, clock: jax.Array, command: jax.Array,
              home: jax.Array) -> jax.Array:
    """Go1 joint targets ``[12]`` (rad) of the gait at global clock ``clock`` for command
    ``(vx m/s, vy m/s, yaw rad/s)``: each leg's thigh sweeps back through stance (foot travel
    ``vx D / f``) and forward through swing while the knee lifts; ``home`` ``[12]`` is the
    standing pose."""
    phases = leg_phases(clock, gait.offsets)
    stance = in_stance(phases, gait.duty)
    u_st = phases / jnp.maximum(gait.duty, 1e-3)
    u_sw = (phases - gait.duty) / jnp.maximum(1.0 - gait.duty, 1e-3)
    sweep = jnp.where(stance, 1.0 - 2.0 * u_st, -1.0 + 2.0 * u_sw)  # +1 forward, -1 back
    side = jnp.array([-1.0, 1.0, -1.0, 1.0])  # right legs -1, left +1
    travel = command[0] * gait.duty / jnp.maximum(gait.freq, 1e-3)  # foot travel per stance (m)
    amp = jnp.clip(travel / (2 * cfg.leg_length), -cfg.max_sweep, cfg.max_sweep)
    amp = amp * (1.0 + cfg.yaw_gain * command[2] * side)
    lift = swing_height(phases, gait.duty, cfg.lift)
    home = home.reshape(4, 3)
    abduction = home[:, 0]  # lateral motion is left to the planner's residual
    thigh = home[:, 1] - amp * sweep + 0.5 * lift
    calf = home[:, 2] - lift
    return jnp.stack([abduction, thigh, calf], axis=-1).reshape(12)


def classify_contacts(contact) -> tuple[str, float]:
    """The named gait whose pattern best explains measured (or scheduled) foot contacts
    ``[T, 4]`` (bool; legs FR, FL, RR, RL), and its score.

    For each named gait, legs with equal offsets should touch down together (correlated contact
    sequences) and legs half a cycle apart alternately (anti-correlated): the score is the mean
    Pearson correlation over its in-phase pairs minus that over its anti-phase pairs (a leg
    that never changes contributes 0). Ties go to the first of trot, pronk, bound, pace.
    """
    c = np.asarray(contact, np.float64)
    if c.ndim != 2 or c.shape[1] != len(LEGS):
        raise ValueError(f"contacts must be [T, {len(LEGS)}], got {c.shape}")
    c = c - c.mean(0)
    norm = np.sqrt((c ** 2).sum(0))
    corr = (c.T @ c) / np.maximum(np.outer(norm, norm), 1e-12)
    corr[norm < 1e-9, :] = corr[:, norm < 1e-9] = 0.0
    scores = {}
    for name, g in NAMED.items():
        o = np.asarray(g.offsets)
        same, anti = [], []
        for i in range(4):
            for j in range(i + 1, 4):
                d = abs((o[i] - o[j]) % 1.0)
                (same if min(d, 1 - d) < 0.1 else anti).append(corr[i, j])
        scores[name] = np.mean(same) - (np.mean(anti) if anti else 0.0)
    best = max(scores, key=scores.get)
    return best, float(scores[best])
