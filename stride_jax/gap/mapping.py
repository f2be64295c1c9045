"""The mapping file of ``stride gap import`` (TOML): which robot the recordings are for, what
they call each joint, and where each log column comes from (:mod:`stride_jax.gap.importer`'s
docstring documents the format). :func:`load_mapping` reads and checks it; errors
(:class:`MappingError`) name the file and the key."""

from __future__ import annotations

import dataclasses
import os
import pathlib
import tomllib
from typing import Any

from stride_jax.gap import logs
from stride_jax.gap.logs import LogError
from stride_jax.sim.model import SimModel

JOINT_GROUPS = ("q", "qd", "cmd", "tau")
VECTOR_GROUPS = {g: tuple(c.rsplit("_", 1)[1] for c in cols) for g, cols in (
    ("base_pos", logs.BASE_COLS[0:3]), ("base_quat", logs.BASE_COLS[3:7]),
    ("base_linvel", logs.BASE_COLS[7:10]), ("base_angvel", logs.BASE_COLS[10:13]),
    ("imu_acc", logs.IMU_COLS[0:3]), ("imu_gyro", logs.IMU_COLS[3:6]))}
HELD = ("cmd_", "imu_")  # zero-order hold; everything else is interpolated
TOP_KEYS = {"robot", "split_gap_s", "msg_types", "joints", "sources", "stamps", "csv",
            "base_linvel_frame"}
SOURCE_KEYS = {"topic", "field", "column", "scale", "offset"}


class MappingError(LogError):
    """A mapping file that cannot be used: says which file, key and what is wrong."""


@dataclasses.dataclass(frozen=True)
class Source:
    """Where one log column comes from: ``topic`` + ``field`` (bags) or ``column`` (CSV);
    ``value = raw * scale + offset``."""

    topic: str | None = None
    field: str | None = None
    column: str | None = None
    scale: float = 1.0
    offset: float = 0.0

    def describe(self) -> str:
        return f"topic {self.topic!r} field {self.field!r}" if self.topic else f"column {self.column!r}"


@dataclasses.dataclass(frozen=True)
class Mapping:
    """A parsed mapping file.

    Attributes:
      path: the mapping file.
      sm: the robot the logs are for.
      columns: log column -> :class:`Source`, every column the log will hold except ``time``.
      time: the CSV time column (None for bags).
      split_gap_s: a pause longer than this starts a new trajectory (None: never).
      stamps: topic -> field of its header stamp.
      msg_types: ROS message definition files (``.msg``) to register.
      delimiter: CSV field separator.
      linvel_body: the base linear velocity source is in the body frame (nav_msgs/Odometry's
        twist is in its child frame): rotated to the world frame with the base quaternion.
    """

    path: pathlib.Path
    sm: SimModel
    columns: dict[str, Source]
    time: Source | None
    split_gap_s: float | None
    stamps: dict[str, str]
    msg_types: tuple[pathlib.Path, ...]
    delimiter: str = ","
    linvel_body: bool = False

    @property
    def has_torque(self) -> bool:
        return any(c.startswith("tau_") for c in self.columns)

    @property
    def has_imu(self) -> bool:
        return any(c.startswith("imu_") for c in self.columns)


# ----------------------------------------------------------------------------- the mapping file


def _robot(d: dict, path: pathlib.Path) -> SimModel:
    from stride_jax.robots import RobotError, mjcf
    from stride_jax.sim import model

    r = d.get("robot")
    try:
        if isinstance(r, dict):
            return model.load(str(path.resolve()))
        if not isinstance(r, str) or not r:
            raise MappingError(f"{path}: 'robot' must name a robot, an MJCF/robot file, or be a "
                               "[robot] table")
        if mjcf.is_path(r) and not os.path.isabs(r):
            r = str((path.parent / r).resolve())
        return model.load(r)
    except RobotError as e:
        raise MappingError(f"{path}: robot: {e}") from e


def _source(v: Any, where: str) -> Source:
    if not isinstance(v, dict):
        raise MappingError(f"{where}: a source is a table {{topic, field}} or {{column}}, got {v!r}")
    unknown = sorted(set(v) - SOURCE_KEYS)
    if unknown:
        raise MappingError(f"{where}: unknown key(s) {unknown}; a source has {sorted(SOURCE_KEYS)}")
    if bool(v.get("column")) == bool(v.get("topic")) or bool(v.get("topic")) != bool(v.get("field")):
        raise MappingError(f"{where}: give either topic and field (bag) or column (CSV)")
    return Source(v.get("topic"), v.get("field"), v.get("column"), v.get("scale", 1.0), v.get("offset", 0.0))


def _number(x: Any, key: str, label: str, where: str) -> float:
    if isinstance(x, dict):
        if label not in x:
            raise MappingError(f"{where}: {key} table has no entry for {label!r}")
        x = x[label]
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        raise MappingError(f"{where}: {key} must be a number (or a table of numbers), got {x!r}")
    return float(x)


def _expand(tmpl: Source, subs: dict[str, str], label: str, where: str) -> Source:
    def sub(s):
        try:
            return None if s is None else s.format(**subs)
        except (KeyError, IndexError, ValueError) as e:
            raise MappingError(f"{where}: cannot fill in {s!r} ({e!r}); placeholders are "
                               f"{{{'}, {'.join(subs)}}}") from None
    return Source(sub(tmpl.topic), sub(tmpl.field), sub(tmpl.column),
                  _number(tmpl.scale, "scale", label, where), _number(tmpl.offset, "offset", label, where))


def load_mapping(path: str | os.PathLike) -> Mapping:
    """Parses and checks a mapping file against its robot (:class:`MappingError` otherwise)."""
    path = pathlib.Path(path)
    if not path.is_file():
        raise MappingError(f"{path}: no such mapping file")
    try:
        d = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as e:
        raise MappingError(f"{path}: not valid TOML ({e})") from e
    unknown = sorted(set(d) - TOP_KEYS)
    if unknown:
        raise MappingError(f"{path}: unknown key(s) {unknown}; known: {sorted(TOP_KEYS)}")
    sm = _robot(d, path)
    lay = logs.layout(sm)
    names = d.get("joints", {})
    if not isinstance(names, dict) or not isinstance(d.get("stamps", {}), dict):
        raise MappingError(f"{path}: [joints] and [stamps] must be tables (name = value)")
    bad = sorted(set(names) - set(lay.joints))
    if bad:
        raise MappingError(f"{path}: [joints] {bad} are not joints of robot {sm.robot.name!r} "
                           f"(its joints: {list(lay.joints)})")
    srcs = d.get("sources")
    if not isinstance(srcs, dict) or not srcs:
        raise MappingError(f"{path}: needs a [sources] table (column or group -> source)")
    tmpl = {k: _source(v, f"{path}: sources.{k}") for k, v in srcs.items()}
    h = logs.header_for(sm, has_torque=True, has_imu=True)
    allowed = set(h.columns()) | set(JOINT_GROUPS) | set(VECTOR_GROUPS)
    unknown = sorted(set(tmpl) - allowed)
    if unknown:
        raise MappingError(f"{path}: sources {unknown} are not columns of robot {sm.robot.name!r}'s "
                           f"logs nor groups {list(JOINT_GROUPS) + list(VECTOR_GROUPS)}")
    cols: dict[str, Source] = {}
    for g in JOINT_GROUPS:
        for j in (lay.joints if g in ("q", "qd") else lay.cmd_joints):
            c, src = f"{g}_{j}", tmpl.get(f"{g}_{j}", tmpl.get(g))
            if src is not None:
                cols[c] = _expand(src, {"joint": str(names.get(j, j))}, j, f"{path}: sources.{c}")
    for g, axes in VECTOR_GROUPS.items():
        for i, a in enumerate(axes):
            c, src = f"{g}_{a}", tmpl.get(f"{g}_{a}", tmpl.get(g))
            if src is not None:
                cols[c] = _expand(src, {"axis": a, "i": str(i)}, a, f"{path}: sources.{c}")
    required = [c for c in logs.header_for(sm, False, False).columns() if c != "time"]
    missing = [c for c in required if c not in cols]
    if missing:
        raise MappingError(f"{path}: no source for column(s) {missing[:8]}{' ...' if len(missing) > 8 else ''} "
                           f"(robot {sm.robot.name!r}); give the group (e.g. sources.q) or the column")
    for g, size in (("tau_", len(lay.cmd_joints)), ("imu_", 6)):
        n = sum(c.startswith(g) for c in cols)
        if 0 < n < size:
            raise MappingError(f"{path}: sources give {n} of the {size} {g}* columns; give all or none")
    if not sm.robot.floating_base and any(c.startswith(("base_", "imu_")) for c in cols):
        raise MappingError(f"{path}: base and IMU columns are logged for floating-base robots only "
                           f"(robot {sm.robot.name!r} has a fixed base)")
    time = None
    if "time" in srcs:
        time = _expand(_source(srcs["time"], f"{path}: sources.time"), {}, "time", f"{path}: sources.time")
    gap = d.get("split_gap_s")
    if gap is not None and not (isinstance(gap, (int, float)) and gap > 0):
        raise MappingError(f"{path}: split_gap_s must be a positive number of seconds, got {gap!r}")
    types = tuple((path.parent / p) for p in d.get("msg_types", ()))
    for p in types:
        if not p.is_file():
            raise MappingError(f"{path}: msg_types: no such file {p}")
    frame = d.get("base_linvel_frame", "world")
    if frame not in ("world", "body"):
        raise MappingError(f"{path}: base_linvel_frame must be 'world' or 'body', got {frame!r}")
    return Mapping(path, sm, cols, time, gap, dict(d.get("stamps", {})), types,
                   d.get("csv", {}).get("delimiter", ","), frame == "body")
