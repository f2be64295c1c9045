"""What each recorded step holds, extracted the same way from MJX data and from MuJoCo's MjData.

All generalised forces are MuJoCo's own split of the equation of motion

    M(q) qdd = tau + qfrc_passive + qfrc_constraint + qfrc_external - qfrc_bias,

with ``tau = qfrc_actuator`` (the applied actuator force), ``qfrc_bias = C(q, qd) qd + g(q)``, and
``qfrc_external`` the hidden disturbances: ``qfrc_applied`` plus pushes (``xfrc_applied`` mapped
through J^T).
Quantities are those of MuJoCo's forward pass at the recorded state, i.e. the ones the next
simulation step integrates.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from stride_jax.sim.model import SimModel


class Record(NamedTuple):
    """One recorded step of one world. Shapes for one world; datasets stack ``[E, T, ...]``."""

    time: np.ndarray  # [] (s)
    q: np.ndarray  # [nq] generalised positions (free joint: position, then quaternion w x y z)
    qd: np.ndarray  # [nv] generalised velocities (free joint: world linear, body angular)
    qdd: np.ndarray  # [nv] MuJoCo's qacc
    ctrl: np.ndarray  # [nu] actuator commands (position targets for servos, torques for motors)
    tau: np.ndarray  # [nv] qfrc_actuator (N, N m)
    qfrc_passive: np.ndarray  # [nv] springs, damping
    qfrc_constraint: np.ndarray  # [nv] contacts, joint limits, dry friction
    qfrc_bias: np.ndarray  # [nv] Coriolis, centrifugal and gravity
    qfrc_external: np.ndarray  # [nv] hidden disturbances (pushes, the pendulum's upright bump)
    foot_force: np.ndarray  # [nfeet] contact normal force per foot (N)
    foot_contact: np.ndarray  # [nfeet] bool: the foot carries a positive normal force
    base_pos: np.ndarray  # [3] world position of the base body (m)
    base_quat: np.ndarray  # [4] its orientation (w x y z)
    base_linvel: np.ndarray  # [3] world-frame linear velocity (m/s); zeros for fixed bases
    base_angvel: np.ndarray  # [3] body-frame angular velocity (rad/s); zeros for fixed bases
    gravity: np.ndarray  # [3] the model's gravity at this step (m/s^2, world frame): tilted
    # under the floor on a sloped episode (Randomization.slope_deg); datasets written before it
    # lack the field (:func:`down_of`)


FIELDS = Record._fields


def _foot_slots(sm: SimModel, contact_geom: np.ndarray) -> np.ndarray:
    """``[ncon]`` index of the foot each contact slot belongs to, or -1."""
    return sm.geom_foot[np.asarray(contact_geom)].max(axis=1) if len(contact_geom) else (
        np.zeros(0, np.int32))


class ContactLayout(NamedTuple):
    """MJX's static contact slots: which foot owns each slot and where its constraint rows are."""

    owner: np.ndarray  # [ncon] foot index or -1
    efc_address: np.ndarray  # [ncon] first constraint row, -1 if the slot is disabled
    n_rows: np.ndarray  # [ncon] rows per slot (pyramidal: 2 (condim - 1); condim 1: 1)
    # Rough ground (a heightfield): a foot's force is the vertical part of its net contact force
    # (see vertical_force); ``sign`` [ncon] is +1 where the foot is the contact's second geom.
    sign: np.ndarray | None = None


def uneven(m) -> bool:
    """Whether the ground is a heightfield (:mod:`stride_jax.sim.terrain`): a foot's contacts
    then have tilted normals and :func:`from_mjx` and :func:`from_mujoco` record the vertical
    component of its net contact force instead of the sum of the contacts' normal forces (equal
    on flat ground). MuJoCo's heightfield gives a sphere several contacts, one per prism it
    touches, with normals tilted up to horizontal when it sinks deep (soft ground), whose normal
    forces partly cancel: their sum would overstate the load."""
    return m.nhfield > 0


@functools.cache
def _jitted_forward():
    from mujoco import mjx

    return jax.jit(lambda mx: mjx.forward(mx, mjx.make_data(mx))._impl.contact)


def mjx_contact_layout(sm: SimModel, mx) -> ContactLayout:
    """Reads the static contact layout of an ``mjx.Model`` (outside any trace). The forward pass
    that lays the contacts out is compiled, not run op by op: eagerly, G1's on rough ground took
    78 s on a 2-core CPU, compiled 7 s."""
    con = _jitted_forward()(mx)
    dim = np.asarray(con.dim)
    geom = np.asarray(con.geom)
    sign = np.where(sm.geom_foot[geom[:, 1]] >= 0, 1.0, -1.0) if uneven(mx) else None
    return ContactLayout(owner=_foot_slots(sm, geom), efc_address=np.asarray(con.efc_address),
                         n_rows=np.where(dim == 1, 1, 2 * (dim - 1)), sign=sign)


def from_mjx(sm: SimModel, d, layout: ContactLayout, gravity) -> Record:
    """Extracts a record from MJX data after ``mjx.forward`` of a model whose gravity is
    ``gravity`` [3] (its ``opt.gravity``)."""
    efc_force = d._impl.efc_force
    foot_force = [jnp.zeros(())] * sm.nfeet
    for c, (f, adr, n) in enumerate(zip(layout.owner, layout.efc_address, layout.n_rows)):
        if f >= 0 and adr >= 0:  # pyramidal cone: the normal force is the sum of the edge forces
            if layout.sign is None:
                foot_force[f] = foot_force[f] + efc_force[adr:adr + n].sum()
            else:  # the vertical part of the contact's force on the foot (world frame)
                pyr, con = efc_force[adr:adr + n], d._impl.contact
                k = np.arange(n // 2)
                local = jnp.concatenate([pyr.sum()[None],
                                         (pyr[2 * k] - pyr[2 * k + 1]) * con.friction[c, k]])
                up = local @ con.frame[c, :len(local), 2]
                foot_force[f] = foot_force[f] + layout.sign[c] * up
    foot_force = jnp.stack(foot_force) if sm.nfeet else jnp.zeros((0,))
    return from_forward(sm, d, foot_force, gravity)


def from_forward(sm: SimModel, d, foot_force: jnp.ndarray, gravity, before=None) -> Record:
    """A record from MJX data holding a forward pass's quantities and the feet's normal forces,
    of a model whose gravity is ``gravity`` [3].

    ``before``: the data whose state (time, qpos, qvel, ctrl) the forward pass was run at, when
    ``d`` is the data after a whole step (MuJoCo Warp: the step's forward-pass quantities stay in
    ``d`` while its state has moved on); by default ``d`` itself.
    """
    s = d if before is None else before
    b = sm.base_body
    floating = sm.robot.floating_base
    qfrc_external = d.qfrc_smooth - d.qfrc_actuator - d.qfrc_passive + d.qfrc_bias
    return Record(
        time=s.time, q=s.qpos, qd=s.qvel, qdd=d.qacc, ctrl=s.ctrl, tau=d.qfrc_actuator,
        qfrc_passive=d.qfrc_passive, qfrc_constraint=d.qfrc_constraint, qfrc_bias=d.qfrc_bias,
        qfrc_external=qfrc_external,
        foot_force=foot_force, foot_contact=foot_force > 0,
        base_pos=d.xpos[b], base_quat=d.xquat[b],
        base_linvel=s.qvel[0:3] if floating else jnp.zeros(3),
        base_angvel=s.qvel[3:6] if floating else jnp.zeros(3),
        gravity=jnp.asarray(gravity, d.qpos.dtype),
    )


def from_mujoco(sm: SimModel, m: mujoco.MjModel, d: mujoco.MjData) -> Record:
    """Extracts a record from MuJoCo data after ``mj_forward``; per-foot forces via mj_contactForce."""
    foot_force = np.zeros(sm.nfeet)
    if sm.nfeet and d.ncon:
        owner = _foot_slots(sm, np.asarray(d.contact.geom))
        wrench = np.zeros(6)
        rough = uneven(m)
        for c in np.flatnonzero(owner >= 0):
            mujoco.mj_contactForce(m, d, int(c), wrench)
            if rough:  # the vertical part of the contact's force on the foot (world frame)
                con = d.contact[int(c)]
                sign = 1.0 if sm.geom_foot[con.geom2] >= 0 else -1.0
                foot_force[owner[c]] += sign * (wrench[:3] @ con.frame.reshape(3, 3)[:, 2])
            else:
                foot_force[owner[c]] += wrench[0]  # contact frame: x is the normal
    b = sm.base_body
    floating = sm.robot.floating_base
    qfrc_external = d.qfrc_smooth - d.qfrc_actuator - d.qfrc_passive + d.qfrc_bias
    return Record(
        time=np.array(d.time), q=d.qpos.copy(), qd=d.qvel.copy(), qdd=d.qacc.copy(),
        ctrl=d.ctrl.copy(), tau=d.qfrc_actuator.copy(), qfrc_passive=d.qfrc_passive.copy(),
        qfrc_constraint=d.qfrc_constraint.copy(), qfrc_bias=d.qfrc_bias.copy(),
        qfrc_external=qfrc_external, foot_force=foot_force, foot_contact=foot_force > 0,
        base_pos=d.xpos[b].copy(), base_quat=d.xquat[b].copy(),
        base_linvel=d.qvel[0:3].copy() if floating else np.zeros(3),
        base_angvel=d.qvel[3:6].copy() if floating else np.zeros(3),
        gravity=m.opt.gravity.copy(),
    )


def down_of(arrays: dict) -> np.ndarray | None:
    """Gravity's unit direction ``[..., 3]`` at every step of a dataset's arrays (or a split's)
    whose gravity is tilted somewhere (sloped episodes), else ``None``: world down throughout,
    or a dataset written before ``Record.gravity`` existed. The models are told it where it is
    not ``None`` (training examples, evaluation windows)."""
    if "gravity" not in arrays:
        return None
    g = np.asarray(arrays["gravity"], np.float64)
    down = g / np.maximum(np.linalg.norm(g, axis=-1, keepdims=True), 1e-12)
    if np.all(np.abs(down - np.array([0.0, 0.0, -1.0])) < 1e-6):
        return None
    return down.astype(np.float32)
