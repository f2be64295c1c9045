"""Finer effects: the joint effects per joint group, encoder offsets, link mass and inertia per body
group, a constant wrench on the base, servo damping.

Names are resolved on first use by :data:`stride_jax.gap.effects.ALL` (so fits, reports and the
benchmark treat them like the library's own), with the groups of :mod:`stride_jax.gap.groups`:

=========================  ====================================================  ===========  =======
name                       what                                                  units        nominal
=========================  ====================================================  ===========  =======
``<joint effect>@<group>``  ``damping``, ``frictionloss``, ``armature``,           as the plain  as the
                           ``kp_scale`` (servo gain), ``torque_scale`` (motor     effect       plain
                           gain), ``torque_limit``, ``servo_damping`` on the                     effect
                           joints of one group (``damping@calf``, ``kp_scale@FR``)
``servo_damping``          servo damping ``kd`` added to every position servo     N m s/rad    0
``encoder_offset@<joint>`` what the joint's encoder adds to its true angle        rad          0
``mass@<group>``           factor on the mass and inertia of the group's links    1            1
``inertia@<group>``        factor on the rotational inertia of the group's links  1            1
                           (``base``: the base body)
``base_wrench``            constant world-frame force at the base's centre of     N, N m       0
                           mass (x, y, z) and torque (x, y, z)
=========================  ====================================================  ===========  =======

What they do in the simulator: an encoder offset ``b`` means the logged angle is ``q + b``: replays
start from ``q_log - b`` and a position servo, which closes its loop on the encoder, pushes with
``kp (u - q - b)`` (the servo's bias term); a motor's torque command does not depend on it.
Servo damping is the servo's ``-kd qd`` term: it passes through the actuator (and its force limit)
where joint damping does not, so the two differ only while servos saturate or where torques are
measured; without either the logs cannot tell them apart (:mod:`stride_jax.gap.screen` reports such
sets). The base wrench acts through ``xfrc_applied`` at every simulation step.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from stride_jax.gap import effects, groups
from stride_jax.gap.effects import Effect, Plan
from stride_jax.sim.model import SimModel

JOINT_EFFECTS = ("damping", "frictionloss", "armature", "kp_scale", "torque_scale", "torque_limit",
                 "servo_damping")
BODY_EFFECTS = ("mass", "inertia")
_DOF_HI = {"damping": 5.0, "frictionloss": 3.0, "armature": 0.3}  # as the plain effects' upper bounds
_SERVO = lambda sm: sm.robot.kp is not None
_MOTOR = lambda sm: sm.robot.kp is None


def _ix(sm: SimModel, group: str | None) -> np.ndarray:
    """Actuator indices of ``group`` (every actuator for None)."""
    if group is None:
        return np.arange(sm.mj.nu)
    return np.asarray(groups.of(sm).joint_index(group))


def _has_group(group: str, families=("type", "limb", "side", "end")):
    def ok(sm):
        return group in groups.of(sm).names(families)
    return ok


def _dof_field(field: str, hi: float, group: str | None) -> tuple:
    def apply(sm, plan, p):
        getattr(plan.mj, field)[sm.act_dof[_ix(sm, group)]] += p[0]
        return plan

    def bounds(sm):
        return np.array([-float(getattr(sm.mj, field)[sm.act_dof[_ix(sm, group)]].min())]), np.array([hi])
    return apply, bounds


def _kp(group):
    def apply(sm, plan, p):
        ix = _ix(sm, group)
        plan.mj.actuator_gainprm[ix, 0] *= p[0]
        plan.mj.actuator_biasprm[ix, 1] *= p[0]
        return plan
    return apply


def _gain(group):
    def apply(sm, plan, p):
        ix = _ix(sm, group)
        plan.mj.actuator_gainprm[ix, 0] *= p[0]
        plan.mj.actuator_biasprm[ix, 1:3] *= p[0]
        plan.mj.actuator_forcerange[ix] *= p[0]
        return plan
    return apply


def _limit(group):
    def apply(sm, plan, p):
        if p[0] == 1.0:
            return plan
        ix = _ix(sm, group)
        ref = effects.reference_force_limit(sm)[ix]
        ok = ix[np.isfinite(ref)]
        plan.mj.actuator_forcelimited[ok] = 1
        plan.mj.actuator_forcerange[ok] = np.stack([-ref[np.isfinite(ref)], ref[np.isfinite(ref)]], 1) * p[0]
        return plan
    return apply


def _servo_damping(group):
    def apply(sm, plan, p):
        plan.mj.actuator_biasprm[_ix(sm, group), 2] -= p[0]
        return plan

    def bounds(sm):
        kd = -sm.mj.actuator_biasprm[_ix(sm, group), 2]
        return np.array([-float(kd.min())]), np.array([5.0])
    return apply, bounds


def _joint_effect(base: str, group: str | None) -> Effect | None:
    """``base`` on the joints of ``group`` (all joints for None: only ``servo_damping`` is new)."""
    applies = _has_group(group) if group else (lambda sm: True)
    name = base if group is None else f"{base}@{group}"
    where = "every position servo" if group is None else f"the {group} joints"
    lib = effects.LIBRARY.get(base)
    if base in ("damping", "frictionloss", "armature"):
        apply, bounds = _dof_field(f"dof_{base}", _DOF_HI[base], group)
        return Effect(name, f"{lib.doc} on {where}", lib.units, (0.0,), bounds, apply, applies)
    if base == "kp_scale":
        return Effect(name, f"servo stiffness scale on {where}", "1", (1.0,), effects._const_bounds(0.3, 1.7),
                      _kp(group), lambda sm: _SERVO(sm) and applies(sm))
    if base == "torque_scale":  # a motor's gain; for servos torque_scale@group is kp_scale's near-twin
        return Effect(name, f"actuator force scale on {where}", "1", (1.0,), effects._const_bounds(0.3, 1.7),
                      _gain(group), lambda sm: _MOTOR(sm) and applies(sm))
    if base == "torque_limit":
        return Effect(name, f"actuator force limit (fraction of nominal) on {where}", "1", (1.0,),
                      effects._const_bounds(0.15, 1.0), _limit(group), applies)
    if base == "servo_damping":
        apply, bounds = _servo_damping(group)
        return Effect(name, f"servo damping kd added on {where}", "N m s/rad", (0.0,), bounds, apply,
                      lambda sm: _SERVO(sm) and applies(sm))
    return None


def _encoder(joint: str) -> Effect:
    def apply(sm, plan, p):
        (a,) = _ix(sm, joint)
        m = plan.mj
        off = np.zeros(sm.mj.nq) if plan.q_offset is None else plan.q_offset.copy()
        off[m.jnt_qposadr[m.actuator_trnid[a, 0]]] += p[0]
        m.actuator_biasprm[a, 0] += m.actuator_biasprm[a, 1] * p[0]  # the servo's loop sees q + b
        return dataclasses.replace(plan, q_offset=off)

    return Effect(f"encoder_offset@{joint}", f"encoder offset of {joint}", "rad", (0.0,),
                  effects._const_bounds(-0.1, 0.1), apply, _has_group(joint, ("joint",)))


def _bodies(sm, group):
    return np.asarray(groups.of(sm).bodies[group], int)


def _body(base: str, group: str) -> Effect:
    def apply(sm, plan, p):
        b = _bodies(sm, group)
        if base == "mass":
            plan.mj.body_mass[b] *= p[0]
        plan.mj.body_inertia[b] *= p[0]
        return plan

    what = "mass and inertia" if base == "mass" else "rotational inertia"
    return Effect(f"{base}@{group}", f"factor on the {what} of the {group} links", "1", (1.0,),
                  effects._const_bounds(0.5, 2.0), apply,
                  lambda sm: len(groups.of(sm).bodies.get(group, ())) > 0)


def _wrench_bounds(sm):
    mg = float(sm.mj.body_subtreemass[sm.base_body]) * float(np.linalg.norm(sm.mj.opt.gravity))
    f, t = 0.3 * mg, 0.05 * mg  # N; N m (a 5 cm lever of a third of the weight)
    return np.array([-f] * 3 + [-t] * 3), np.array([f] * 3 + [t] * 3)


def _wrench(sm, plan, p):
    w = np.zeros(6) if plan.wrench is None else plan.wrench.copy()
    return dataclasses.replace(plan, wrench=w + p)


BASE_WRENCH = Effect("base_wrench", "constant external wrench on the base (world frame)", "N, N m",
                     (0.0,) * 6, _wrench_bounds, _wrench, lambda sm: sm.robot.floating_base,
                     labels=("fx", "fy", "fz", "tx", "ty", "tz"))


def resolve(name: str) -> Effect | None:
    """The finer effect called ``name``, or None. Whether it applies to a robot (its group exists)
    is the effect's ``applies``."""
    if name == "base_wrench":
        return BASE_WRENCH
    if name == "servo_damping":
        return _joint_effect("servo_damping", None)
    base, sep, group = name.partition("@")
    if not sep or not group:
        return None
    if base in JOINT_EFFECTS:
        return _joint_effect(base, group)
    if base == "encoder_offset":
        return _encoder(group)
    if base in BODY_EFFECTS:
        return _body(base, group)
    return None


def parent(name: str) -> str:
    """The all-joints effect a finer variant refines (``damping@calf`` -> ``damping``), or the name."""
    base, _, _ = name.partition("@")
    return base


def children(sm: SimModel, name: str) -> list[str]:
    """The variants of joint effect ``name`` on each joint group (type, limb, side and end
    families) that apply to robot ``sm``: ``damping`` -> ``damping@hip``, ..., ``damping@rear``;
    none for another name."""
    if name not in JOINT_EFFECTS:
        return []
    out = [f"{name}@{grp}" for grp in groups.of(sm).names(("type", "limb", "side", "end"))]
    return [n for n in out if effects.ALL[n].applies(sm)]


def candidates(sm: SimModel) -> list[str]:
    """Every finer effect that applies to robot ``sm``: the joint effects on each group of the type,
    limb, side and end families, servo damping, one encoder offset per joint, mass and inertia of
    each type and limb body group, inertia of the base, the base wrench."""
    g = groups.of(sm)
    out = [n for n in ("servo_damping", "base_wrench") if effects.ALL[n].applies(sm)]
    for grp in g.names(("type", "limb", "side", "end")):
        out += [f"{b}@{grp}" for b in JOINT_EFFECTS]
    out += [f"encoder_offset@{j}" for j in g.families.get("joint", {})]
    out += [f"{b}@{grp}" for grp in g.bodies if grp != "base" for b in BODY_EFFECTS]
    out += ["inertia@base"]
    return [n for n in out if effects.ALL[n].applies(sm)]


def unions(sm: SimModel, names: list[str]) -> dict[str, tuple[str, ...]]:
    """The joint-effect candidates of ``names`` whose joints are the disjoint union of limb groups
    that ``names`` hold with the same effect: ``{"damping@left": ("damping@FL", "damping@RL"), ...}``
    (the side and end groups of a quadruped, the sides of a humanoid's four limbs).

    To first order such an effect's replays move as the sum of its limbs' do, so the screen adds
    their sensitivity columns instead of replaying it (:func:`stride_jax.gap.screen.columns`): a
    quarter fewer replays for the Go1's screen. Its actual replays come with its one-step check
    and its full fit."""
    g = groups.of(sm)
    limbs = g.families.get("limb", {})
    have = set(names)
    out = {}
    for fam in ("side", "end"):
        for grp, ix in g.families.get(fam, {}).items():
            parts = [lb for lb, lix in limbs.items() if set(lix) <= set(ix)]
            if len(parts) < 2 or set().union(*(set(limbs[lb]) for lb in parts)) != set(ix):
                continue
            for b in JOINT_EFFECTS:
                if f"{b}@{grp}" in have and all(f"{b}@{lb}" in have for lb in parts):
                    out[f"{b}@{grp}"] = tuple(f"{b}@{lb}" for lb in parts)
    return out


effects.register_resolver(resolve)  # effects.ALL names the finer effects
