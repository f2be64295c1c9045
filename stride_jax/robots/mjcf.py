"""Any robot: a :class:`~stride_jax.robots.base.Robot` built on the fly from an MJCF file, alone or
described by a small robot file (TOML).

``get("path/arm.xml")`` takes the MJCF as it is: its own actuators (all joint actuators, either all
position servos or all motors), its own timestep, a control period of about 20 ms. A robot file
says more, in a ``[robot]`` table (the same table may sit in a log mapping file,
:mod:`stride_jax.gap.importer`, so that one file serves ``stride gap import`` and ``--robot``)::

    [robot]
    name = "arm"                     # the name logs carry (default: the MJCF file's stem)
    mjcf = "arm.xml"                 # relative to this file; ~ and $VARS are expanded
    joints = ["shoulder", "elbow"]   # actuated joints, in actuator (command) order
    actuators = "position"           # "mjcf" (the file's own), "position" (servos) or "motor"
    kp = 20.0                        # position servos: N m/rad, a number or {joint = value}
    kd = 1.0                         # position servos: N m s/rad (default 0)
    torque_limit = 10.0              # N m; motors need it (their control range), servos may have it
    control_period_s = 0.01          # a multiple of the MJCF timestep (default: about 20 ms)
    home_key = "home"                # keyframe of the home pose (default: the MJCF's qpos0)
    base_body = "forearm"            # where a payload sits (default: the free joint's body, or the
                                     # body of the last actuated joint of a fixed-base robot)
    weld = ["finger_joint1"]         # joints the logs do not carry: removed, their bodies welded
                                     # (with the tendons, equalities and actuators on them)
    feet = [{name = "foot", geoms = ["foot_geom"], site = "foot_site"}]   # floating base only

Every joint left (except a free joint) must appear in the logs. ``stride gap simulate`` drives such
a robot with :class:`SineExplorer` (smooth random commands around the home pose).
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import pathlib
import tomllib
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from stride_jax.robots import base
from stride_jax.robots.base import RobotError

ACTUATORS = ("mjcf", "position", "motor")
KEYS = {"name", "mjcf", "joints", "actuators", "kp", "kd", "torque_limit", "control_period_s",
        "home_key", "base_body", "weld", "feet"}


def is_path(name: str) -> bool:
    """Whether a ``--robot`` value names a file rather than a registered robot."""
    return name.endswith((".xml", ".toml")) or os.sep in name


# ----------------------------------------------------------------------------- exploration


class SineParams(NamedTuple):
    key: jax.Array
    qpos0: jax.Array  # [nq]
    amps: jax.Array  # [3, nu] fractions of the half range
    freqs: jax.Array  # [3, nu] (Hz)
    phases: jax.Array  # [3, nu] (rad)


@dataclasses.dataclass(frozen=True)
class SineExplorer:
    """Smooth random commands: per actuator ``centre + half * sum_k a_k sin(2 pi f_k t + phi_k)``
    with three sinusoids (``a_k`` in [0, 1/3], ``f_k`` in [0.2, 2] Hz), clipped to the control range.
    Fixed-base robots start within 0.1 rad (or m) of the home pose, at rest.

    Attributes:
      centre, half: ``[nu]`` command centre (servos: the joint's home angle) and amplitude.
      jitter: whether the initial pose is perturbed (fixed base only).
    """

    centre: tuple[float, ...]
    half: tuple[float, ...]
    jitter: bool = True

    def sample(self, key: jax.Array, info: base.ModelInfo) -> SineParams:
        k_ep, k_q, k_a, k_f, k_p = jax.random.split(key, 5)
        nu = len(self.centre)
        dq = jax.random.uniform(k_q, (info.nq,), minval=-0.1, maxval=0.1) if self.jitter else 0.0
        return SineParams(key=k_ep, qpos0=jnp.asarray(info.qpos0) + dq,
                          amps=jax.random.uniform(k_a, (3, nu), maxval=1 / 3),
                          freqs=jax.random.uniform(k_f, (3, nu), minval=0.2, maxval=2.0),
                          phases=jax.random.uniform(k_p, (3, nu), maxval=2 * jnp.pi))

    def reset(self, params: SineParams, info: base.ModelInfo):
        return params.qpos0, jnp.zeros(info.nv)

    def act(self, params: SineParams, info: base.ModelInfo, step, qpos, qvel):
        t = step * info.ctrl_dt
        wave = jnp.sum(params.amps * jnp.sin(2 * jnp.pi * params.freqs * t + params.phases), 0)
        u = jnp.asarray(self.centre) + jnp.asarray(self.half) * wave
        return jnp.clip(u, info.ctrl_lo, info.ctrl_hi)


# ----------------------------------------------------------------------------- the robot file


def _per_joint(value, joints: tuple[str, ...], key: str, where: str) -> np.ndarray | None:
    """A number or a ``{joint: number}`` table as ``[len(joints)]`` (None if not given)."""
    if value is None:
        return None
    if isinstance(value, dict):
        unknown = sorted(set(value) - set(joints))
        missing = [j for j in joints if j not in value]
        if unknown or missing:
            raise RobotError(f"{where}: {key}: joints {unknown} are not actuated, {missing} have no "
                             "value (give a number or one value per actuated joint)")
        value = [value[j] for j in joints]
    try:
        arr = np.broadcast_to(np.asarray(value, np.float64), (len(joints),)).copy()
    except (ValueError, TypeError):
        raise RobotError(f"{where}: {key} must be a number or a table of numbers per joint, "
                         f"got {value!r}") from None
    return arr


def _spec_edit(joints, kind, kp, kd, limit, weld, where):
    """The edit that welds the listed joints and installs the actuators (in place)."""

    def edit(spec: mujoco.MjSpec) -> None:
        names = {j.name for j in spec.joints}
        gone = [w for w in weld if w not in names]
        if gone:
            raise RobotError(f"{where}: weld: no joint named {gone} in the MJCF")
        if weld:
            _drop_welded(spec, set(weld))
        if kind == "mjcf":
            return
        for a in list(spec.actuators):
            spec.delete(a)
        for i, j in enumerate(joints):
            a = spec.add_actuator(name=f"stride_{j}", target=j, trntype=mujoco.mjtTrn.mjTRN_JOINT)
            if kind == "position":
                a.set_to_position(kp=float(kp[i]), kv=float(kd[i]))
                jnt = spec.joint(j)
                limited = jnt.limited != mujoco.mjtLimited.mjLIMITED_FALSE and jnt.range[0] < jnt.range[1]
                lo, hi = jnt.range if limited else (-np.pi, np.pi)
                a.ctrllimited, a.ctrlrange = mujoco.mjtLimited.mjLIMITED_TRUE, [lo, hi]
            else:
                a.set_to_motor()
                a.ctrllimited, a.ctrlrange = mujoco.mjtLimited.mjLIMITED_TRUE, [-limit[i], limit[i]]
            if limit is not None:
                a.forcelimited, a.forcerange = mujoco.mjtLimited.mjLIMITED_TRUE, [-limit[i], limit[i]]

    return edit


def _drop_welded(spec: mujoco.MjSpec, weld: set[str]) -> None:
    """Deletes the ``weld`` joints, the tendons that wrap them, the equalities and actuators on
    either, so that the model compiles without them (a gripper's coupled fingers, say)."""
    m = spec.compile()
    jid = {mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, w) for w in weld}
    tendons = set()
    for t in range(m.ntendon):
        a, n = m.tendon_adr[t], m.tendon_num[t]
        if any(m.wrap_type[k] == mujoco.mjtWrap.mjWRAP_JOINT and m.wrap_objid[k] in jid
               for k in range(a, a + n)):
            tendons.add(m.tendon(t).name)
    gone = weld | tendons
    for e in list(spec.equalities):
        if e.type in (mujoco.mjtEq.mjEQ_JOINT, mujoco.mjtEq.mjEQ_TENDON) and ({e.name1, e.name2} - {""}) & gone:
            spec.delete(e)
    for a in list(spec.actuators):
        if a.target in gone:
            spec.delete(a)
    for t in [t for t in spec.tendons if t.name in tendons]:
        spec.delete(t)
    for j in [j for j in spec.joints if j.name in weld]:
        spec.delete(j)


def _mjcf_path(value, folder: pathlib.Path, where: str) -> pathlib.Path:
    if not isinstance(value, str) or not value:
        raise RobotError(f"{where}: robot.mjcf must name an MJCF file")
    path = pathlib.Path(os.path.expandvars(os.path.expanduser(value)))
    path = path if path.is_absolute() else folder / path
    if not path.is_file():
        raise RobotError(f"{where}: robot.mjcf: no such file {path}")
    return path


def from_table(d: dict[str, Any], folder: str | os.PathLike = ".", where: str = "robot") -> base.Robot:
    """The robot that a ``[robot]`` table describes (paths relative to ``folder``)."""
    unknown = sorted(set(d) - KEYS)
    if unknown:
        raise RobotError(f"{where}: unknown robot key(s) {unknown}; known: {sorted(KEYS)}")
    path = _mjcf_path(d.get("mjcf"), pathlib.Path(folder), where)
    kind = d.get("actuators", "mjcf")
    if kind not in ACTUATORS:
        raise RobotError(f"{where}: robot.actuators must be one of {ACTUATORS}, got {kind!r}")
    weld = tuple(d.get("weld", ()))

    def load_spec() -> mujoco.MjSpec:
        try:
            return mujoco.MjSpec.from_file(str(path))
        except ValueError as e:
            raise RobotError(f"{path}: MuJoCo cannot parse it: {e}") from e

    spec = load_spec()
    free = [j for j in spec.joints if j.type == mujoco.mjtJoint.mjJNT_FREE]
    movable = [j.name for j in spec.joints if j.type in (mujoco.mjtJoint.mjJNT_HINGE,
                                                          mujoco.mjtJoint.mjJNT_SLIDE)]
    if kind == "mjcf":
        welded = load_spec()
        _spec_edit((), kind, None, None, None, weld, where)(welded)
        joints = _mjcf_actuated(welded, path)
        if "joints" in d and tuple(d["joints"]) != joints:
            raise RobotError(f"{where}: robot.joints {list(d['joints'])} differ from the joints the "
                             f"MJCF's actuators drive, in order: {list(joints)}")
    else:
        joints = tuple(d.get("joints") or [j for j in movable if j not in weld])
    bad = [j for j in joints if j not in movable or j in weld]
    if bad:
        raise RobotError(f"{where}: robot.joints {bad}: not hinge or slide joints of {path} (or welded)")
    if not joints:
        raise RobotError(f"{where}: no actuated joints")
    kp = _per_joint(d.get("kp"), joints, "kp", where)
    kd = _per_joint(d.get("kd", 0.0), joints, "kd", where)
    limit = _per_joint(d.get("torque_limit"), joints, "torque_limit", where)
    if kind == "position" and kp is None:
        raise RobotError(f"{where}: robot.actuators = 'position' needs kp (N m/rad)")
    if kind == "motor" and limit is None:
        raise RobotError(f"{where}: robot.actuators = 'motor' needs torque_limit (N m): it is the "
                         "motors' control range")
    edit = _spec_edit(joints, kind, kp, kd, limit, weld, where)
    probe = load_spec()
    edit(probe)
    try:
        m = probe.compile()
    except ValueError as e:
        raise RobotError(f"{path}: does not compile after the robot file's edits: {e}") from e
    if kind == "mjcf":
        kp, kd = _servo_gains(m, path)
    ts = float(m.opt.timestep)
    ctrl_dt = float(d.get("control_period_s", ts * max(1, round(0.02 / ts))))
    floating = bool(free)
    if floating and m.jnt_type[0] != mujoco.mjtJoint.mjJNT_FREE:
        raise RobotError(f"{path}: the free joint must be the model's first joint")
    body = d.get("base_body") or (free[0].parent.name if floating else
                                  m.body(m.jnt_bodyid[m.joint(joints[-1]).id]).name)
    feet = tuple(base.Foot(f["name"], tuple(f["geoms"]), f["site"]) for f in d.get("feet", ()))
    qpos0 = m.qpos0.copy()
    if d.get("home_key"):
        qpos0 = m.key(d["home_key"]).qpos.copy()
    qa = m.jnt_qposadr[m.actuator_trnid[:, 0]]
    lo, hi = m.actuator_ctrlrange[:, 0], m.actuator_ctrlrange[:, 1]
    if kp is not None:
        centre = np.clip(qpos0[qa], lo, hi)
        half = 0.5 * np.minimum(hi - lo, 2.0)
    else:
        centre, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    return base.Robot(
        name=str(d.get("name") or path.stem), source=str(path), load_spec=load_spec, edit_spec=edit,
        joints=joints, feet=feet, base_body=body, floating_base=floating, ctrl_dt=ctrl_dt,
        home_key=d.get("home_key"), kp=None if kp is None else tuple(map(float, kp)),
        kd=None if kp is None else tuple(map(float, kd)),
        explorer=SineExplorer(tuple(map(float, centre)), tuple(map(float, half)), jitter=not floating),
        randomization=base.Randomization(), episode_s=5.0, min_base_height=0.0)


def _mjcf_actuated(spec: mujoco.MjSpec, path: pathlib.Path) -> tuple[str, ...]:
    m = spec.compile()
    if m.nu == 0:
        raise RobotError(f"{path}: the MJCF has no actuators; write a robot file with "
                         "actuators = 'position' (kp, kd) or 'motor' (torque_limit)")
    if (m.actuator_trntype != mujoco.mjtTrn.mjTRN_JOINT).any():
        raise RobotError(f"{path}: only joint actuators are supported (tendon/site ones are not); "
                         "write a robot file with actuators = 'position' or 'motor'")
    return tuple(m.joint(m.actuator_trnid[i, 0]).name for i in range(m.nu))


def _servo_gains(m: mujoco.MjModel, path: pathlib.Path):
    """``(kp, kd)`` of the MJCF's own actuators if all are position servos, ``(None, None)`` if all
    are motors; mixed kinds are refused (a log has one command kind)."""
    servo = (m.actuator_biastype == mujoco.mjtBias.mjBIAS_AFFINE) & (m.actuator_biasprm[:, 1] < 0)
    motor = (m.actuator_biastype == mujoco.mjtBias.mjBIAS_NONE) & (
        m.actuator_gaintype == mujoco.mjtGain.mjGAIN_FIXED)
    if servo.all():
        return m.actuator_gainprm[:, 0].copy(), -m.actuator_biasprm[:, 2]
    if motor.all():
        return None, None
    raise RobotError(f"{path}: the actuators must be all position servos or all motors; write a "
                     "robot file with actuators = 'position' or 'motor'")


def file_key(path: str) -> str:
    """A digest of the file's text (empty if it is missing): what a cache of its robot keys on."""
    p = pathlib.Path(path)
    return hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else ""


def load(path: str) -> base.Robot:
    """The robot of an MJCF file (``.xml``) or of a robot/mapping file's ``[robot]`` table (``.toml``)."""
    p = pathlib.Path(path)
    if not p.is_file():
        raise RobotError(f"robot {path!r}: no such file (a robot is a registered name, an MJCF "
                         ".xml or a robot file .toml)")
    if p.suffix != ".toml":
        return from_table({"mjcf": str(p.resolve())}, p.parent, str(p))
    try:
        d = tomllib.loads(p.read_text())
    except tomllib.TOMLDecodeError as e:
        raise RobotError(f"{p}: not valid TOML ({e})") from e
    table = d.get("robot")
    if not isinstance(table, dict):
        raise RobotError(f"{p}: needs a [robot] table with at least mjcf = 'path.xml'")
    return from_table(table, p.parent, str(p))
