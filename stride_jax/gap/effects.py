"""The effects library: parametric changes that the nominal model lacks, singly or combined.

Each :class:`Effect` has a parameter vector with a nominal value that reproduces the nominal model
exactly, box bounds for fitting (which may depend on the robot), and either edits a copy of the
``mujoco.MjModel`` (model side) or sets a field of the controller-side :class:`Plan` (how the
commanded controls reach the actuators). Effects combine by applying each in turn.

In the library (candidates the diagnosis fits):

================  ========================================================  ============  =======
name              what                                                      units         nominal
================  ========================================================  ============  =======
damping           viscous damping added to every actuated joint             N m s/rad     0
frictionloss      Coulomb (dry) friction added to every actuated joint      N m           0
armature          rotor inertia added to every actuated joint               kg m^2        0
delay             actuator delay (commands reach the motors late)           sim steps     0
torque_scale      factor on the actuator force (motor constant error)       1             1
torque_limit      factor on the actuator force limit (saturation)           1             1
kp_scale          factor on the position servos' stiffness (PD mismatch)    1             1
ground_friction   factor on the sliding friction of every contact           1             1
contact_softness  factor on the contact time constant (solref)              1             1
payload           mass added to the base body (inertia scaled alike)        kg            0
com_offset        offset of the base body's centre of mass (x, y, z)        m             0
deadzone          servo ignores position errors below delta (torque         rad or N m    0
                  commands below delta for motors), at the control rate
================  ========================================================  ============  =======

``torque_scale`` scales the force limit too; ``kp_scale`` does not: for servos without damping
(the Go1's) they differ only while the servos saturate, and the diagnosis reports such near-ties
as indistinguishable. Servo damping (``kd``) is not a separate effect: without measured torques ``-kd qd`` and joint
damping are the same dynamics. ``delay`` is counted in simulation steps, so that delays shorter
than one control period can be represented; it is fitted on a grid, never by a local optimiser.

Outside the library (``OUT_OF_LIBRARY``, used by the blind benchmark to plant effects the
diagnosis cannot name): ``joint_stiffness`` (a spring pulling every actuated joint to its home
angle) and ``quadratic_drag`` (a joint torque ``-c qd |qd|``, applied at the control rate).
"""

from __future__ import annotations

import copy
import dataclasses
from typing import Callable, Mapping

import mujoco
import numpy as np

from stride_jax.sim import randomize
from stride_jax.sim.model import SimModel


@dataclasses.dataclass(frozen=True)
class Plan:
    """A model plus the controller-side effects, everything the simulator needs to run a world.

    Attributes:
      mj: the (edited copy of the) MuJoCo model.
      delay: actuator delay in simulation steps.
      deadzone: servo position-error (or motor torque) dead band, applied at each control update.
      drag: coefficient of the hidden quadratic joint drag (N m s^2/rad^2); out of library.
      q_offset: ``[nq]`` what the encoders add to the true joint positions (rad; None: nothing):
        replays start from ``q_log - q_offset`` (:mod:`stride_jax.gap.finer`, encoder offsets).
      wrench: ``[6]`` constant external wrench on the base (world-frame force in N at its centre
        of mass, torque in N m; None: none).
    """

    mj: mujoco.MjModel
    delay: int = 0
    deadzone: float = 0.0
    drag: float = 0.0
    q_offset: np.ndarray | None = None
    wrench: np.ndarray | None = None


@dataclasses.dataclass(frozen=True)
class Effect:
    """One parametric effect.

    Attributes:
      name: identifier.
      doc: one line for reports.
      units: of the parameters.
      nominal: parameter values that reproduce the nominal model.
      bounds: ``bounds(sm) -> (lo [k], hi [k])`` for fitting.
      apply: ``apply(sm, plan, p) -> plan`` (model-side effects edit ``plan.mj`` in place: it is
        already a private copy).
      applies: whether the effect makes sense for the robot.
      integer: fitted on an integer grid (delay).
      in_library: a candidate of the diagnosis.
      labels: name of each parameter.
    """

    name: str
    doc: str
    units: str
    nominal: tuple[float, ...]
    bounds: Callable[[SimModel], tuple[np.ndarray, np.ndarray]]
    apply: Callable[[SimModel, Plan, np.ndarray], Plan]
    applies: Callable[[SimModel], bool] = lambda sm: True
    integer: bool = False
    in_library: bool = True
    labels: tuple[str, ...] = ("value",)

    @property
    def size(self) -> int:
        return len(self.nominal)


def _act_dofs(sm: SimModel) -> np.ndarray:
    return np.asarray(sm.act_dof)


def _add_dof(field: str):
    def apply(sm, plan, p):
        getattr(plan.mj, field)[_act_dofs(sm)] += p[0]
        return plan
    return apply


def _add_dof_bounds(field: str, hi: float):
    def bounds(sm):
        lo = -float(getattr(sm.mj, field)[_act_dofs(sm)].min())
        return np.array([lo]), np.array([hi])
    return bounds


def _const_bounds(lo, hi):
    return lambda sm: (np.atleast_1d(np.asarray(lo, float)), np.atleast_1d(np.asarray(hi, float)))


def _torque_scale(sm, plan, p):
    # A motor-constant error scales the whole force, its limit included (the driver limits current).
    plan.mj.actuator_gainprm[:, 0] *= p[0]
    plan.mj.actuator_biasprm[:, 1:3] *= p[0]
    plan.mj.actuator_forcerange[:] *= p[0]
    return plan


def reference_force_limit(sm: SimModel) -> np.ndarray:
    """``[nu]`` the nominal actuator force limit: the force range where set, else what the
    control range can command (motors: |ctrl| * gain)."""
    m = sm.mj
    lim = np.where(m.actuator_forcelimited.astype(bool), m.actuator_forcerange[:, 1], np.inf)
    motor = np.abs(m.actuator_biasprm[:, :3]).sum(1) == 0
    cmd = np.abs(m.actuator_ctrlrange).max(1) * np.abs(m.actuator_gainprm[:, 0])
    return np.where(np.isinf(lim) & motor, cmd, lim)


def _torque_limit(sm, plan, p):
    ref = reference_force_limit(sm)
    if p[0] == 1.0:  # nominal: leave the model as it is (an unlimited servo stays unlimited)
        return plan
    ok = np.isfinite(ref)
    plan.mj.actuator_forcelimited[ok] = 1
    plan.mj.actuator_forcerange[ok] = np.stack([-ref[ok], ref[ok]], 1) * p[0]
    return plan


def _kp_scale(sm, plan, p):
    plan.mj.actuator_gainprm[:, 0] *= p[0]
    plan.mj.actuator_biasprm[:, 1] *= p[0]
    return plan


def _ground_friction(sm, plan, p):
    plan.mj.geom_friction[:, 0] *= p[0]
    plan.mj.pair_friction[:, :2] *= p[0]
    return plan


def _softness(sm, plan, p):
    plan.mj.geom_solref[:, 0] *= p[0]
    plan.mj.pair_solref[:, 0] *= p[0]
    return plan


def _payload(sm, plan, p):
    randomize.add_payload(plan.mj, sm.base_body, p[0])
    return plan


def _payload_bounds(sm):
    return np.array([-0.3 * float(sm.mj.body_mass[sm.base_body])]), np.array(
        [0.5 * float(sm.mj.body_mass[sm.base_body])])


def _com(sm, plan, p):
    plan.mj.body_ipos[sm.base_body] += p
    return plan


def _delay(sm, plan, p):
    return dataclasses.replace(plan, delay=int(round(p[0])))


def _delay_bounds(sm):
    return np.array([0.0]), np.array([float(3 * sm.n_substeps)])  # up to three control periods


def _deadzone(sm, plan, p):
    return dataclasses.replace(plan, deadzone=float(p[0]))


def _deadzone_bounds(sm):
    hi = 0.1 if sm.robot.kp is not None else 0.3 * float(reference_force_limit(sm).min())
    return np.array([0.0]), np.array([hi])


def _stiffness(sm, plan, p):
    if p[0] == 0.0:  # nominal: leave the spring reference as it is
        return plan
    jnt = sm.mj.actuator_trnid[:, 0]
    plan.mj.jnt_stiffness[jnt] += p[0]
    qadr = sm.mj.jnt_qposadr[jnt]
    plan.mj.qpos_spring[qadr] = np.asarray(sm.info.qpos0, np.float64)[qadr]
    return plan


def _drag(sm, plan, p):
    return dataclasses.replace(plan, drag=float(p[0]))


_HAS_FEET = lambda sm: sm.nfeet > 0
_SERVO = lambda sm: sm.robot.kp is not None

LIBRARY: dict[str, Effect] = {e.name: e for e in [
    Effect("damping", "joint viscous damping (added)", "N m s/rad", (0.0,),
           _add_dof_bounds("dof_damping", 5.0), _add_dof("dof_damping")),
    Effect("frictionloss", "joint Coulomb friction (added)", "N m", (0.0,),
           _add_dof_bounds("dof_frictionloss", 3.0), _add_dof("dof_frictionloss")),
    Effect("armature", "rotor inertia (added)", "kg m^2", (0.0,),
           _add_dof_bounds("dof_armature", 0.3), _add_dof("dof_armature")),
    Effect("delay", "actuator delay", "sim steps", (0.0,), _delay_bounds, _delay, integer=True),
    Effect("torque_scale", "actuator force scale", "1", (1.0,), _const_bounds(0.3, 1.7),
           _torque_scale),
    Effect("torque_limit", "actuator force limit (fraction of nominal)", "1", (1.0,),
           _const_bounds(0.15, 1.0), _torque_limit),
    Effect("kp_scale", "servo stiffness scale (PD gain mismatch)", "1", (1.0,),
           _const_bounds(0.3, 1.7), _kp_scale, applies=_SERVO),
    Effect("ground_friction", "contact sliding friction scale", "1", (1.0,),
           _const_bounds(0.2, 2.0), _ground_friction, applies=_HAS_FEET),
    Effect("contact_softness", "contact time constant scale (solref)", "1", (1.0,),
           _const_bounds(0.5, 5.0), _softness, applies=_HAS_FEET),
    Effect("payload", "payload mass on the base", "kg", (0.0,), _payload_bounds, _payload),
    Effect("com_offset", "base centre-of-mass offset", "m", (0.0, 0.0, 0.0),
           _const_bounds([-0.08] * 3, [0.08] * 3), _com, labels=("x", "y", "z")),
    Effect("deadzone", "servo dead band", "rad (servo) or N m (motor)", (0.0,), _deadzone_bounds,
           _deadzone),
]}

OUT_OF_LIBRARY: dict[str, Effect] = {e.name: e for e in [
    Effect("joint_stiffness", "spring to the home angle on every actuated joint", "N m/rad", (0.0,),
           _const_bounds(0.0, 50.0), _stiffness, in_library=False),
    Effect("quadratic_drag", "joint torque -c qd|qd| (control rate)", "N m s^2/rad^2", (0.0,),
           _const_bounds(0.0, 1.0), _drag, in_library=False),
]}

# Functions ``name -> Effect | None`` that name effects beyond the table above; the finer
# effects register theirs when :mod:`stride_jax.gap.finer` is imported (by the package).
_RESOLVERS: list[Callable[[str], "Effect | None"]] = []


def register_resolver(resolve: Callable[[str], "Effect | None"]) -> None:
    """Adds ``resolve`` to the lookup of :data:`ALL` by name (once)."""
    if resolve not in _RESOLVERS:
        _RESOLVERS.append(resolve)


class _Registry(dict):
    """``ALL``: the effects above, and the finer ones (``damping@calf``, ``encoder_offset@FR_hip_joint``,
    ``base_wrench``, ...) resolved by name on first use (:mod:`stride_jax.gap.finer` registers
    its resolver)."""

    def __missing__(self, name):
        e = next((e for e in (r(name) for r in _RESOLVERS) if e is not None), None)
        if e is None:
            raise KeyError(name)
        self[name] = e
        return e

    def __contains__(self, name):
        try:
            self[name]
        except KeyError:
            return False
        return True


ALL: dict[str, Effect] = _Registry(LIBRARY | OUT_OF_LIBRARY)

Applied = Mapping[str, "np.ndarray | float | list"]


def candidates(sm: SimModel) -> list[Effect]:
    """The library effects that apply to robot ``sm``."""
    return [e for e in LIBRARY.values() if e.applies(sm)]


def build(sm: SimModel, applied: Applied | None = None) -> Plan:
    """The :class:`Plan` of the nominal model with ``applied`` (name -> parameters) on top.

    An empty or None ``applied`` (or every effect at its nominal value) gives the nominal model
    (a copy of it, bit-for-bit equal).
    """
    plan = Plan(mj=copy.copy(sm.mj))  # MjModel's copy is a deep copy
    for name, p in (applied or {}).items():
        if name not in ALL:
            raise KeyError(f"unknown effect {name!r}; known: {', '.join(ALL)}")
        e = ALL[name]
        p = np.atleast_1d(np.asarray(p, np.float64))
        if p.shape != (e.size,):
            raise ValueError(f"effect {name!r} takes {e.size} parameter(s) ({', '.join(e.labels)}), "
                             f"got shape {list(p.shape)}")
        if not e.applies(sm):
            raise ValueError(f"effect {name!r} does not apply to robot {sm.robot.name!r}")
        plan = e.apply(sm, plan, p)
    return plan


# ----------------------------------------------------------------------------- controller side


def substep_commands(cmd: np.ndarray, t: np.ndarray, delay: int, n_sub: int) -> np.ndarray:
    """The command each actuator sees at every simulation step of control steps ``t``.

    ``cmd [T, nu]`` commands of one trajectory (held for a control period each), ``t [B]`` control
    steps; returns ``[B, n_sub, nu]``: simulation step ``s`` of control step ``t`` sees the
    command issued ``delay`` simulation steps earlier (the first command before the log starts).
    """
    i = t[:, None] * n_sub + np.arange(n_sub)[None, :] - delay
    return cmd[np.clip(np.floor_divide(i, n_sub), 0, len(cmd) - 1)]


def dead_band(u: np.ndarray, q_act: np.ndarray, delta: float, servo: bool) -> np.ndarray:
    """Commands after the dead band: servos ignore position errors below ``delta``
    (``u' = q + sign(e) max(|e| - delta, 0)`` with ``e = u - q``); motors ignore small torques.

    ``u [..., nu]`` commands, ``q_act [..., nu]`` actuated joint positions at the control update.
    """
    if delta == 0.0:
        return u
    if servo:
        e = u - q_act
        return q_act + np.sign(e) * np.maximum(np.abs(e) - delta, 0.0)
    return np.sign(u) * np.maximum(np.abs(u) - delta, 0.0)
