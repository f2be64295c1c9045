"""The log format a real robot writes, its writer and its reader (with validation), and the export
of simulated runs in it. Cleaning and estimation on the logs: :mod:`stride_jax.gap.filters`.

Format (``stride-gap-log`` version 1): one folder per log set,

* ``header.json``::

    {"format": "stride-gap-log", "version": 1, "robot": "go1",
     "joint_names": ["FR_hip_joint", ...],        # order of the q_/qd_/tau_ columns
     "command_joints": ["FR_hip_joint", ...],     # joint each command drives (actuator order)
     "command_kind": "position" | "torque",       # servo targets (rad) or motor torques (N m)
     "control_period_s": 0.02,                    # nominal period of the command updates
     "floating_base": true, "has_torque": true, "has_imu": true,
     "units": {...}, "notes": "free text",
     "velocity_noise": {"qd": 0.04, "base_linvel": 0.03, "base_angvel": 0.01}}   # optional

  ``velocity_noise`` (optional): the standard deviation of the logged velocities' white noise,
  in their columns' units: ``qd`` for every joint, ``qd_<j>`` for one (over ``qd``),
  ``base_linvel`` and ``base_angvel`` for a floating base; when given, every velocity column
  must be covered. The diagnosis then computes its noise floor from it instead of reading it
  off the residuals (:func:`velocity_std`, :func:`stride_jax.gap.regions.noise_floor_of`).

* one CSV per trajectory (any ``*.csv`` in the folder), comma separated, one header row, one
  row per sample, columns (``<j>`` is a joint name):

  ============================  ===========================================================
  ``time``                      seconds, strictly increasing
  ``q_<j>``, ``qd_<j>``         joint position (rad) and velocity (rad/s), every joint
  ``cmd_<j>``                   command sent at this sample and held until the next one
                                (servo target in rad or torque in N m), every commanded joint
  ``tau_<j>`` (optional)        measured joint torque (N m)
  ``base_pos_{x,y,z}``          floating base only: estimator position, world frame (m)
  ``base_quat_{w,x,y,z}``       estimator orientation, body to world (unit quaternion)
  ``base_linvel_{x,y,z}``       estimator linear velocity, world frame (m/s)
  ``base_angvel_{x,y,z}``       angular velocity, body frame (rad/s)
  ``imu_acc_{x,y,z}`` (opt.)    specific force, body frame (m/s^2)
  ``imu_gyro_{x,y,z}`` (opt.)   angular rate, body frame (rad/s)
  ============================  ===========================================================

No accelerations and no contact forces: the tool estimates what it needs. The reader rejects a
missing column, a joint that the robot lacks (or a robot joint the log lacks), non-monotonic
timestamps, and NaN or non-numeric entries with a :class:`LogError` naming file, column and row.
Recordings of a real robot (ROS 2 bags, MCAP, CSV) become such a folder with ``stride gap import``
(:mod:`stride_jax.gap.importer`).
"""

from __future__ import annotations

import csv
import dataclasses
import io as _io
import json
import math
import os
import pathlib
from typing import NamedTuple

import mujoco
import numpy as np

from stride_jax import io
from stride_jax.sim.model import SimModel

FORMAT = "stride-gap-log"
VERSION = 1
BASE_COLS = (tuple(f"base_pos_{a}" for a in "xyz") + tuple(f"base_quat_{a}" for a in "wxyz")
             + tuple(f"base_linvel_{a}" for a in "xyz") + tuple(f"base_angvel_{a}" for a in "xyz"))
IMU_COLS = tuple(f"imu_acc_{a}" for a in "xyz") + tuple(f"imu_gyro_{a}" for a in "xyz")
UNITS = {"time": "s", "q": "rad", "qd": "rad/s", "cmd_position": "rad", "cmd_torque": "N m",
         "tau": "N m", "base_pos": "m (world)", "base_quat": "w x y z, body to world",
         "base_linvel": "m/s (world)", "base_angvel": "rad/s (body)", "imu_acc": "m/s^2 (body)",
         "imu_gyro": "rad/s (body)"}


class LogError(ValueError):
    """A log that cannot be used: says which file, column and row, and what is wrong."""


@dataclasses.dataclass(frozen=True)
class Header:
    """The parsed ``header.json``."""

    robot: str
    joint_names: tuple[str, ...]
    command_joints: tuple[str, ...]
    command_kind: str
    control_period_s: float
    floating_base: bool
    has_torque: bool
    has_imu: bool
    notes: str = ""
    velocity_noise: dict = dataclasses.field(default_factory=dict)

    def columns(self) -> list[str]:
        """The CSV columns this header requires, in the order the writer writes them."""
        cols = ["time"] + [f"q_{j}" for j in self.joint_names] + [f"qd_{j}" for j in self.joint_names]
        cols += [f"cmd_{j}" for j in self.command_joints]
        if self.has_torque:
            cols += [f"tau_{j}" for j in self.command_joints]
        if self.floating_base:
            cols += list(BASE_COLS)
        if self.has_imu:
            cols += list(IMU_COLS)
        return cols


class Trajectory(NamedTuple):
    """One trajectory in the simulator's coordinates (MuJoCo qpos/qvel order of the robot).

    ``t [T]`` (s), ``q [T, nq]``, ``qd [T, nv]``, ``cmd [T, nu]`` (actuator order), ``tau [T, nu]``
    or None (measured torques), ``imu [T, 6]`` or None (acc, gyro), ``name`` (file stem).
    """

    name: str
    t: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    cmd: np.ndarray
    tau: np.ndarray | None
    imu: np.ndarray | None


# ----------------------------------------------------------------------------- layout


class Layout(NamedTuple):
    """Where the log's named joints sit in the robot's qpos/qvel/ctrl."""

    joints: tuple[str, ...]  # hinge/slide joints, model order
    qadr: np.ndarray  # [nj] qpos index
    vadr: np.ndarray  # [nj] qvel index
    cmd_joints: tuple[str, ...]  # joint driven by each actuator


def layout(sm: SimModel) -> Layout:
    """The joint layout of a compiled robot (every non-free joint is logged)."""
    m = sm.mj
    js = [j for j in range(m.njnt) if m.jnt_type[j] != mujoco.mjtJoint.mjJNT_FREE]
    for j in js:
        if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_BALL:
            raise LogError(f"robot {sm.robot.name!r}: ball joints are not supported by the log format")
    return Layout(tuple(m.joint(j).name for j in js), m.jnt_qposadr[js].astype(int),
                  m.jnt_dofadr[js].astype(int), tuple(sm.robot.joints))


def header_for(sm: SimModel, has_torque: bool, has_imu: bool, notes: str = "",
               velocity_noise: dict | None = None) -> Header:
    lay = layout(sm)
    return Header(robot=sm.robot.name, joint_names=lay.joints, command_joints=lay.cmd_joints,
                  command_kind="position" if sm.robot.kp is not None else "torque",
                  control_period_s=sm.robot.ctrl_dt, floating_base=sm.robot.floating_base,
                  has_torque=has_torque, has_imu=has_imu and sm.robot.floating_base, notes=notes,
                  velocity_noise=dict(velocity_noise or {}))


def velocity_std(h: Header, sm: SimModel, where: str = "header.json") -> np.ndarray | None:
    """``[nv]`` standard deviation of each logged velocity's noise (qvel order) from the header's
    ``velocity_noise``; None when the header gives none. :class:`LogError` naming the key or the
    channel on an unknown key, a value that is not a finite number >= 0, or a velocity column
    left uncovered."""
    spec = h.velocity_noise
    if not spec:
        return None
    names = _velocity_channels(sm, layout(sm))
    unknown = sorted(set(spec) - set(names) - {"qd"})
    if unknown:
        raise LogError(f"{where}: velocity_noise keys {unknown} are not velocity channels of robot "
                       f"{sm.robot.name!r} (use 'qd', 'qd_<joint>'"
                       + (", 'base_linvel', 'base_angvel')" if sm.robot.floating_base else ")"))
    for k, v in spec.items():
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
            raise LogError(f"{where}: velocity_noise[{k!r}] must be a finite number >= 0, got {v!r}")
    # a joint's own level over the joints' common one
    std = np.array([spec.get(n, spec.get("qd", np.nan) if n.startswith("qd_") else np.nan)
                    for n in names], float)
    missing = list(dict.fromkeys(n for n, s in zip(names, std, strict=True) if np.isnan(s)))
    if missing:
        raise LogError(f"{where}: velocity_noise leaves {missing} uncovered (give every velocity "
                       f"channel a noise level, or none)")
    return std


def _velocity_channels(sm: SimModel, lay: Layout) -> list[str]:
    """The name of each qvel entry as ``velocity_noise`` keys it."""
    names = [""] * sm.mj.nv
    if sm.robot.floating_base:
        names[:6] = ["base_linvel"] * 3 + ["base_angvel"] * 3
    for j, a in zip(lay.joints, lay.vadr, strict=True):
        names[a] = f"qd_{j}"
    return names


# ----------------------------------------------------------------------------- writing


def write(out_dir: str | os.PathLike, sm: SimModel, trajs: list[Trajectory], notes: str = "",
          velocity_noise: dict | None = None) -> pathlib.Path:
    """Writes ``trajs`` as a log folder (``header.json`` + ``traj_<name>.csv``), atomically per
    file; ``velocity_noise``: the header's optional noise levels (checked as the reader checks)."""
    if not trajs:
        raise LogError("no trajectories to write")
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    has_tau = all(tr.tau is not None for tr in trajs)
    has_imu = all(tr.imu is not None for tr in trajs)
    h = header_for(sm, has_tau, has_imu, notes, velocity_noise)
    velocity_std(h, sm, "the log's header to write")
    lay = layout(sm)
    hdr = dataclasses.asdict(h) | {"format": FORMAT, "version": VERSION, "units": UNITS}
    for tr in trajs:
        cols = [tr.t[:, None], tr.q[:, lay.qadr], tr.qd[:, lay.vadr], tr.cmd]
        if h.has_torque:
            cols.append(tr.tau)
        if h.floating_base:
            cols += [tr.q[:, :7], tr.qd[:, :6]]  # pos, quat; world linvel, body angvel
        if h.has_imu:
            cols.append(tr.imu)
        table = np.concatenate([np.asarray(c, np.float64) for c in cols], axis=1)
        buf = _io.StringIO()
        buf.write(",".join(h.columns()) + "\n")
        np.savetxt(buf, table, delimiter=",", fmt="%.10g")
        io.atomic_write_text(out / f"{tr.name}.csv", buf.getvalue())
    io.atomic_write_text(out / "header.json", json.dumps(hdr, indent=1))
    return out


# ----------------------------------------------------------------------------- reading


def read_header(folder: str | os.PathLike) -> Header:
    path = pathlib.Path(folder) / "header.json"
    if not path.is_file():
        raise LogError(f"{path}: missing (a log folder holds header.json and one CSV per trajectory)")
    try:
        d = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise LogError(f"{path}: not valid JSON ({e})") from e
    if d.get("format") != FORMAT or d.get("version") != VERSION:
        raise LogError(f"{path}: format {d.get('format')!r} version {d.get('version')!r}; this reader "
                       f"reads {FORMAT!r} version {VERSION}")
    fields = [f.name for f in dataclasses.fields(Header)]
    missing = [f for f in fields if f not in d and f not in ("notes", "velocity_noise")]
    if missing:
        raise LogError(f"{path}: missing keys {missing}")
    h = Header(**{k: d[k] for k in fields if k in d})
    h = dataclasses.replace(h, joint_names=tuple(h.joint_names), command_joints=tuple(h.command_joints))
    if h.command_kind not in ("position", "torque"):
        raise LogError(f"{path}: command_kind must be 'position' or 'torque', got {h.command_kind!r}")
    if not (h.control_period_s > 0):
        raise LogError(f"{path}: control_period_s must be positive, got {h.control_period_s}")
    if not isinstance(h.velocity_noise, dict):
        raise LogError(f"{path}: velocity_noise must be an object of noise levels by channel, got "
                       f"{h.velocity_noise!r}")
    return h


def check_header(h: Header, sm: SimModel, where: str) -> Layout:
    """Joint names, command joints and base type of the log against the robot."""
    lay = layout(sm)
    if h.robot != sm.robot.name:
        raise LogError(f"{where}: log is for robot {h.robot!r}, diagnosing {sm.robot.name!r}")
    unknown = [j for j in h.joint_names if j not in lay.joints]
    absent = [j for j in lay.joints if j not in h.joint_names]
    if unknown or absent:
        raise LogError(f"{where}: joint-name mismatch with robot {sm.robot.name!r}: log joints not "
                       f"in the robot {unknown}, robot joints missing from the log {absent}")
    if tuple(h.command_joints) != lay.cmd_joints:
        raise LogError(f"{where}: command_joints {list(h.command_joints)} do not match the robot's "
                       f"actuated joints {list(lay.cmd_joints)} (same names, actuator order)")
    if h.floating_base != sm.robot.floating_base:
        raise LogError(f"{where}: floating_base={h.floating_base}, robot {sm.robot.name!r} has "
                       f"floating_base={sm.robot.floating_base}")
    if abs(h.control_period_s - sm.robot.ctrl_dt) > 1e-9:
        raise LogError(f"{where}: control_period_s {h.control_period_s} differs from the robot's "
                       f"control period {sm.robot.ctrl_dt} s (resample the commands first)")
    return lay


def _read_csv(path: pathlib.Path, required: list[str]) -> tuple[list[str], np.ndarray]:
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    if not rows:
        raise LogError(f"{path}: empty file")
    cols = [c.strip() for c in rows[0]]
    missing = [c for c in required if c not in cols]
    if missing:
        raise LogError(f"{path}: missing column(s) {missing[:8]}{' ...' if len(missing) > 8 else ''}")
    dup = sorted({c for c in cols if cols.count(c) > 1})
    if dup:
        raise LogError(f"{path}: duplicate column(s) {dup}")
    data = np.empty((len(rows) - 1, len(cols)))
    for i, row in enumerate(rows[1:]):
        if len(row) != len(cols):
            raise LogError(f"{path}: row {i + 1} (line {i + 2}) has {len(row)} fields, the header {len(cols)}")
        for k, v in enumerate(row):
            try:
                data[i, k] = float(v) if v.strip() else math.nan
            except ValueError:
                raise LogError(f"{path}: column {cols[k]!r}, row {i + 1} (line {i + 2}): not a number "
                               f"({v!r})") from None
    return cols, data


def read_csv(path: str | os.PathLike, h: Header, lay: Layout, nq: int, nv: int) -> Trajectory:
    """Reads and validates one trajectory CSV against its header."""
    path = pathlib.Path(path)
    required = h.columns()
    cols, data = _read_csv(path, required)
    if len(data) < 3:
        raise LogError(f"{path}: {len(data)} rows; a trajectory needs at least 3 samples")
    idx = {c: k for k, c in enumerate(cols)}
    bad = ~np.isfinite(data[:, [idx[c] for c in required]])
    if bad.any():
        r, c = np.argwhere(bad)[0]
        raise LogError(f"{path}: column {required[c]!r}, row {r + 1} (line {r + 2}): NaN, inf or empty")
    col = lambda names: data[:, [idx[n] for n in names]]
    t = data[:, idx["time"]]
    dt = np.diff(t)
    if (dt <= 0).any():
        r = int(np.flatnonzero(dt <= 0)[0]) + 1
        raise LogError(f"{path}: column 'time', row {r + 1} (line {r + 2}): timestamps must increase "
                       f"strictly ({t[r - 1]!r} then {t[r]!r})")
    q = np.zeros((len(t), nq))
    qd = np.zeros((len(t), nv))
    order = [h.joint_names.index(j) for j in lay.joints]
    q[:, lay.qadr] = col([f"q_{h.joint_names[i]}" for i in order])
    qd[:, lay.vadr] = col([f"qd_{h.joint_names[i]}" for i in order])
    if h.floating_base:
        q[:, :7] = col(BASE_COLS[:7])
        qd[:, :6] = col(BASE_COLS[7:])
        norm = np.linalg.norm(q[:, 3:7], axis=1)
        if (np.abs(norm - 1) > 0.05).any():
            r = int(np.flatnonzero(np.abs(norm - 1) > 0.05)[0])
            raise LogError(f"{path}: columns 'base_quat_*', row {r + 1} (line {r + 2}): quaternion norm "
                           f"{norm[r]:.3f}, expected 1")
        q[:, 3:7] /= norm[:, None]
    cmd = col([f"cmd_{j}" for j in h.command_joints])
    tau = col([f"tau_{j}" for j in h.command_joints]) if h.has_torque else None
    imu = col(IMU_COLS) if h.has_imu else None
    return Trajectory(path.stem, t, q, qd, cmd, tau, imu)


def read(folder: str | os.PathLike, sm: SimModel) -> tuple[Header, list[Trajectory]]:
    """Reads a log folder for robot ``sm``; :class:`LogError` on anything unusable."""
    folder = pathlib.Path(folder)
    if not folder.is_dir():
        raise LogError(f"{folder}: not a folder")
    h = read_header(folder)
    lay = check_header(h, sm, str(folder / "header.json"))
    velocity_std(h, sm, str(folder / "header.json"))
    files = sorted(folder.glob("*.csv"))
    if not files:
        raise LogError(f"{folder}: no trajectory CSV files")
    return h, [read_csv(f, h, lay, sm.mj.nq, sm.mj.nv) for f in files]


# ----------------------------------------------------------------------------- export of sim runs


def imu_from_sim(q: np.ndarray, qd: np.ndarray, qdd: np.ndarray, gravity=(0, 0, -9.81)) -> np.ndarray:
    """Ideal IMU at the base origin ``[T, 6]``: body-frame specific force and angular rate."""
    w, x, y, z = q[:, 3:7].T
    # Rotation body -> world, rows of R; a_body = R^T (a_world - g).
    R = np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
                  np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
                  np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], 1)
    f = qdd[:, :3] - np.asarray(gravity)
    return np.concatenate([np.einsum("tji,tj->ti", R, f), qd[:, 3:6]], axis=1)


def from_records(sm: SimModel, arrays: dict[str, np.ndarray], names: list[str] | None = None,
                 with_torque: bool = True, with_imu: bool = True) -> list[Trajectory]:
    """Trajectories from simulated records (dataset arrays ``[E, T, ...]`` with ``valid [E, T]``).

    Each episode is cut at its first invalid step. Measured torque = the actuator force at the
    driven dof (``tau``); the IMU is ideal. Episodes with fewer than 3 valid steps are dropped.
    """
    valid = np.asarray(arrays["valid"], bool)
    out = []
    for e in range(valid.shape[0]):
        n = int(np.logical_and.accumulate(valid[e]).sum())
        if n < 3:
            continue
        g = lambda k: np.asarray(arrays[k][e, :n], np.float64)
        q, qd = g("q"), g("qd")
        tau = g("tau")[:, sm.act_dof] if with_torque else None
        imu = imu_from_sim(q, qd, g("qdd"), sm.mj.opt.gravity) if (
            with_imu and sm.robot.floating_base) else None
        name = names[e] if names else f"traj_{e:03d}"
        out.append(Trajectory(name, g("time"), q, qd, g("ctrl"), tau, imu))
    return out


def export_dataset(dataset_dir: str | os.PathLike, out_dir: str | os.PathLike) -> pathlib.Path:
    """Writes a ``stride data`` dataset folder as a log folder (every episode one CSV)."""
    from stride_jax.sim import dataset, model

    ds = dataset.load(dataset_dir)
    sm = model.load(ds.meta["robot"])
    return write(out_dir, sm, from_records(sm, ds.arrays),
                 notes=f"exported from simulated dataset {dataset_dir}")
