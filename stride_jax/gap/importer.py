"""``stride gap import``: a real robot's recordings -- ROS 2 bags, MCAP files, plain CSV files --
as the documented log folder (:mod:`stride_jax.gap.logs`), through a small mapping file (TOML).

Mapping file (every key but ``robot`` and ``[sources]`` optional)::

    robot = "go1"                  # registered name, MJCF/robot file (relative to this file),
                                   # or an inline [robot] table (stride_jax.robots.mjcf)
    split_gap_s = 0.5              # a pause longer than this in any source starts a new trajectory
    base_linvel_frame = "world"    # or "body" (nav_msgs/Odometry): rotated to world by base_quat
    msg_types = ["msg/LowState.msg"]   # ROS message definitions the bag does not embed

    [joints]                       # robot joint -> what the recording calls it: {joint} below
    FR_hip_joint = 0               # (default: the robot's own joint name)

    [sources]                      # a column group or one column -> where it comes from
    q   = {topic = "/lowstate", field = "motor_state[{joint}].q"}
    qd  = {topic = "/lowstate", field = "motor_state[{joint}].dq"}
    cmd = {topic = "/lowcmd", field = "motor_cmd[{joint}].q"}
    tau = {topic = "/lowstate", field = "motor_state[{joint}].tau_est"}        # optional
    base_quat = {topic = "/lowstate", field = "imu_state.quaternion[{i}]"}    # {i}: 0..3, w x y z
    q_FR_hip_joint = {topic = "/lowstate", field = "motor_state[0].q", scale = -1}   # one column

    [stamps]                       # a topic's time from a header stamp, not the recording time
    "/lowstate" = "header.stamp"

Groups are the log's column prefixes: ``q``, ``qd`` (every joint), ``cmd``, ``tau`` (every
commanded joint), ``base_pos``, ``base_quat``, ``base_linvel``, ``base_angvel``, ``imu_acc``,
``imu_gyro`` (axes ``{axis}`` = x y z, or w x y z for the quaternion, ``{i}`` = their index).
A source is ``{topic, field}`` in a bag or ``{column}`` in a CSV, with ``scale`` and ``offset``
(``value = raw * scale + offset``; a number, or a table per joint or axis). ``time`` is a CSV
column (``time = {column = "t_us", scale = 1e-6}``); bags time each message when it was recorded
(or by ``[stamps]``).

Fields: ``a.b.c``, ``arr[3]``, ``arr[{joint}]``, and ``position[name=FR_hip]``: the element of
``position`` at the index where the sibling array ``name`` holds ``FR_hip`` (sensor_msgs/JointState),
or, for an array of messages, the element whose ``name`` field is ``FR_hip``. A time stamp
(``sec``/``nanosec``) reads as seconds.

Every signal keeps its own clock until the end: the samples are put on the robot's control grid
with :mod:`stride_jax.gap.filters` (states and torques linearly, the quaternion normalised, commands
and IMU by zero-order hold), each trajectory from the latest first sample to the earliest last
sample of its sources, its time starting at 0. Errors (:class:`LogError`) name the mapping or
recording file and the topic, field or column. The mapping file itself is read by
:mod:`stride_jax.gap.mapping`.
"""

from __future__ import annotations

import csv
import os
import pathlib
import re
from typing import Any, Callable

import numpy as np

from stride_jax.gap import filters, logs
from stride_jax.gap.logs import LogError
from stride_jax.gap.mapping import HELD, Mapping, MappingError, load_mapping  # noqa: F401 (API)

# ----------------------------------------------------------------------------- message fields

_SEG = re.compile(r"^([A-Za-z_]\w*)((?:\[[^\]]*\])*)$")


def _compile_field(field: str, ns: bool = False) -> Callable[[Any], Any]:
    """``field`` (``a.b[3].c``, ``position[name=FR_hip]``) as a getter; ``ValueError`` on bad syntax.
    A time stamp reads as seconds (float), or as integer nanoseconds with ``ns``."""
    steps: list[tuple[str, Any]] = []
    for seg in field.split("."):
        m = _SEG.match(seg.strip())
        if not m:
            raise ValueError(f"bad field syntax at {seg!r}")
        steps.append(("attr", m.group(1)))
        for idx in re.findall(r"\[([^\]]*)\]", m.group(2)):
            if "=" in idx:
                k, v = (s.strip() for s in idx.split("=", 1))
                steps.append(("select", (k, v)))
            elif re.fullmatch(r"\s*\d+\s*", idx):
                steps.append(("index", int(idx)))
            else:
                raise ValueError(f"bad index [{idx}] in {seg!r}: a number or key=value")

    def get(msg):
        x, parent, where = msg, None, ""
        for kind, arg in steps:
            if kind == "attr":
                if not hasattr(x, arg):
                    raise KeyError(f"no field {arg!r}" + (f" in {where!r}" if where else ""))
                parent, x, where = x, getattr(x, arg), f"{where}.{arg}".lstrip(".")
            elif kind == "index":
                if arg >= len(x):
                    raise KeyError(f"{where!r} has {len(x)} elements, index {arg} asked")
                x, where = x[arg], f"{where}[{arg}]"
            else:
                key, val = arg
                if len(x) and hasattr(x[0], key):  # an array of messages: match its field
                    hits = [i for i, e in enumerate(x) if str(getattr(e, key)) == val]
                    pick = lambda i: x[i]
                else:  # a number array: the index where the sibling array holds the value
                    if not hasattr(parent, key):
                        raise KeyError(f"no field {key!r} beside {where!r} to select [{key}={val}]")
                    hits = [i for i, e in enumerate(getattr(parent, key)) if str(e) == val]
                    pick = lambda i: x[i] if i < len(x) else None
                if not hits or pick(hits[0]) is None:
                    raise KeyError(f"no element [{key}={val}] in {where!r}")
                x, where = pick(hits[0]), f"{where}[{key}={val}]"
        if hasattr(x, "sec") and hasattr(x, "nanosec"):
            return int(x.sec) * 10**9 + int(x.nanosec) if ns else float(x.sec) + 1e-9 * float(x.nanosec)
        if ns:
            raise TypeError(f"{where!r} is not a time stamp (sec, nanosec)")
        return x

    return get


def _number_of(x, what: str) -> float:
    try:
        v = float(x)
    except (TypeError, ValueError):
        raise LogError(f"{what}: not a number ({type(x).__name__} {str(x)[:60]!r}); point the "
                       "field at a numeric element") from None
    return v


# ----------------------------------------------------------------------------- sources


Stream = tuple[np.ndarray, np.ndarray]  # (t [N] seconds, values [N])


def _typestore(mp: Mapping):
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    for p in mp.msg_types:
        parts = p.with_suffix("").parts
        name = "/".join(parts[-3:]) if len(parts) >= 3 and parts[-2] == "msg" else f"{parts[-2]}/msg/{parts[-1]}"
        try:
            store.register(get_types_from_msg(p.read_text(), name))
        except Exception as e:  # rosbags' parser errors have no common base
            raise MappingError(f"{mp.path}: msg_types: {p} ({name}): {e}") from e
    return store


def read_bag(path: str | os.PathLike, mp: Mapping) -> dict[str, Stream]:
    """The mapped columns of a ROS 2 bag (folder, ``.mcap`` or ``.db3``) as ``column -> (t, x)``."""
    try:
        from rosbags.highlevel import AnyReader, AnyReaderError
    except ImportError as e:
        raise LogError(f"{path}: reading bags needs the rosbags package (pip install rosbags)") from e

    path = pathlib.Path(path)
    by_topic: dict[str, list[str]] = {}
    for c, s in mp.columns.items():
        if s.topic is None:
            raise MappingError(f"{mp.path}: sources.{c} is a CSV column ({s.column!r}); a bag needs "
                               "topic and field")
        by_topic.setdefault(s.topic, []).append(c)
    getters = {}
    for c, s in mp.columns.items():
        try:
            getters[c] = _compile_field(s.field)
        except ValueError as e:
            raise MappingError(f"{mp.path}: sources.{c}: field {s.field!r}: {e}") from None
    try:
        stamp = {t: _compile_field(f, ns=True) for t, f in mp.stamps.items()}
    except ValueError as e:
        raise MappingError(f"{mp.path}: stamps: {e}") from None
    rows: dict[str, list] = {t: [] for t in by_topic}
    times: dict[str, list] = {t: [] for t in by_topic}
    try:
        with AnyReader([path], default_typestore=_typestore(mp)) as reader:
            have = {c.topic: c for c in reader.connections}
            absent = [t for t in by_topic if t not in have]
            if absent:
                raise LogError(f"{path}: topic(s) {absent} (for {[by_topic[t][0] for t in absent]}) not "
                               f"in the bag; it has {sorted(have)}")
            conns = [c for c in reader.connections if c.topic in by_topic]
            for conn, ts, raw in reader.messages(connections=conns):
                topic = conn.topic
                msg = reader.deserialize(raw, conn.msgtype)
                row = []
                for c in by_topic[topic]:
                    try:
                        x = getters[c](msg)
                    except KeyError as e:
                        raise LogError(f"{path}: topic {topic!r} ({conn.msgtype}), field "
                                       f"{mp.columns[c].field!r} for column {c!r}: {e.args[0]}") from None
                    row.append(_number_of(x, f"{path}: topic {topic!r}, field {mp.columns[c].field!r} "
                                             f"for column {c!r}"))
                rows[topic].append(row)
                if topic in stamp:
                    try:
                        times[topic].append(stamp[topic](msg))
                    except (KeyError, TypeError, ValueError) as e:
                        raise LogError(f"{path}: topic {topic!r}: stamp field {mp.stamps[topic]!r}: "
                                       f"{e}") from None
                else:
                    times[topic].append(ts)
    except AnyReaderError as e:
        raise LogError(f"{path}: not a readable ROS bag ({e})") from e
    except FileNotFoundError as e:
        raise LogError(f"{path}: no such bag ({e})") from e
    out = {}
    empty = [t for t in by_topic if not rows[t]]
    if empty:
        raise LogError(f"{path}: topic(s) {empty} have no messages")
    ns0 = min(min(v) for v in times.values())  # seconds from here: float64 keeps nanoseconds
    for topic, cs in by_topic.items():
        vals = np.asarray(rows[topic], np.float64)
        t = 1e-9 * (np.asarray(times[topic], np.int64) - ns0)
        for k, c in enumerate(cs):
            s = mp.columns[c]
            out[c] = (t, vals[:, k] * s.scale + s.offset)
    return out


def read_table(path: str | os.PathLike, mp: Mapping) -> dict[str, Stream]:
    """The mapped columns of a CSV file (one header row) as ``column -> (t, x)``."""
    path = pathlib.Path(path)
    if mp.time is None or mp.time.column is None:
        raise MappingError(f"{mp.path}: a CSV needs sources.time = {{column = ...}}")
    need = {"time": mp.time} | mp.columns
    for c, s in need.items():
        if s.column is None:
            raise MappingError(f"{mp.path}: sources.{c} is a bag field ({s.topic!r}); a CSV needs column")
    try:
        with open(path, newline="") as f:
            rows = list(csv.reader(f, delimiter=mp.delimiter))
    except (OSError, UnicodeDecodeError) as e:
        raise LogError(f"{path}: cannot read it as CSV ({e})") from e
    if len(rows) < 2:
        raise LogError(f"{path}: no data rows")
    head = [h.strip() for h in rows[0]]
    missing = sorted({s.column for s in need.values()} - set(head))
    if missing:
        raise LogError(f"{path}: no column(s) {missing[:8]} (wanted by the mapping {mp.path.name}); "
                       f"it has {head[:12]}{' ...' if len(head) > 12 else ''}")
    idx = {h: k for k, h in enumerate(head)}
    out = {}
    for c, s in need.items():
        k = idx[s.column]
        v = np.empty(len(rows) - 1)
        for i, row in enumerate(rows[1:]):
            try:
                v[i] = float(row[k])
            except (ValueError, IndexError):
                got = row[k] if k < len(row) else "<missing>"
                raise LogError(f"{path}: column {s.column!r} (for {c!r}), row {i + 1} (line {i + 2}): "
                               f"not a number ({got!r})") from None
        if not np.isfinite(v).all():
            r = int(np.flatnonzero(~np.isfinite(v))[0])
            raise LogError(f"{path}: column {s.column!r} (for {c!r}), row {r + 1} (line {r + 2}): NaN or inf")
        out[c] = (v - v[0]) * s.scale if c == "time" else v * s.scale + s.offset  # see below
    t = out.pop("time")  # from the first row: seconds since 1970 in float64 lose the microseconds
    if (np.diff(t) <= 0).any():
        r = int(np.flatnonzero(np.diff(t) <= 0)[0]) + 1
        raise LogError(f"{path}: column {mp.time.column!r} (time), row {r + 1} (line {r + 2}): "
                       f"timestamps must increase strictly ({t[r - 1]!r} then {t[r]!r})")
    return {c: (t, v) for c, v in out.items()}


# ----------------------------------------------------------------------------- onto the grid


def _clean(stream: Stream) -> Stream:
    """Sorted by time, the last of equal timestamps kept (bags may record out of order)."""
    t, x = stream
    order = np.argsort(t, kind="stable")
    t, x = t[order], x[order]
    keep = np.append(np.diff(t) > 0, True)
    return t[keep], x[keep]


def segments(streams: dict[str, Stream], gap_s: float | None, dt: float) -> list[tuple[float, float]]:
    """Time spans every stream covers, split where any stream pauses longer than ``gap_s``. A held
    stream (commands, IMU) covers one control period ``dt`` past its last sample."""
    start = max(t[0] for t, _ in streams.values())
    end = min(t[-1] + (dt if c.startswith(HELD) else 0.0) for c, (t, _) in streams.items())
    cuts = []
    if gap_s is not None:
        for c, (t, _) in streams.items():
            k = np.flatnonzero(np.diff(t) > gap_s)
            cuts += [(t[i] + (dt if c.startswith(HELD) else 0.0), t[i + 1]) for i in k]
    spans, lo = [], start
    for a, b in sorted(cuts):
        if a > lo and a <= end:
            spans.append((lo, a))
        lo = max(lo, b)
    if lo < end:
        spans.append((lo, end))
    return spans


def to_trajectories(streams: dict[str, Stream], mp: Mapping, name: str) -> list[logs.Trajectory]:
    """The streams of one recording on the robot's control grid, one trajectory per span of
    :func:`segments` (spans shorter than 3 samples are dropped)."""
    sm, lay = mp.sm, logs.layout(mp.sm)
    dt = sm.robot.ctrl_dt
    streams = {c: _clean(s) for c, s in streams.items()}
    out = []
    for k, (a, b) in enumerate(segments(streams, mp.split_gap_s, dt)):
        t = a + dt * np.arange(int(np.floor((b - a) / dt + 1e-6)) + 1)
        if len(t) < 3:
            continue

        def grid(cols):
            x = [streams[c] for c in cols]
            return np.stack([filters.hold(s[0], s[1], t, dt) if c.startswith(HELD) else
                             np.interp(t, s[0], s[1]) for c, s in zip(cols, x)], axis=1)

        q, qd = np.zeros((len(t), sm.mj.nq)), np.zeros((len(t), sm.mj.nv))
        q[:, lay.qadr] = grid([f"q_{j}" for j in lay.joints])
        qd[:, lay.vadr] = grid([f"qd_{j}" for j in lay.joints])
        if sm.robot.floating_base:
            q[:, :3] = grid(list(logs.BASE_COLS[:3]))
            quat = np.stack([streams[c][1] for c in logs.BASE_COLS[3:7]], 1)
            ts = streams[logs.BASE_COLS[3]][0]
            if any(len(streams[c][0]) != len(ts) or (streams[c][0] != ts).any() for c in logs.BASE_COLS[4:7]):
                raise LogError(f"{name}: base_quat_w..z must come from one topic (one clock)")
            q[:, 3:7] = filters.interp_quat(ts, quat, t)
            qd[:, :6] = grid(list(logs.BASE_COLS[7:]))
            if mp.linvel_body:
                qd[:, :3] = np.einsum("tij,tj->ti", _rotation(q[:, 3:7]), qd[:, :3])
        cmd = grid([f"cmd_{j}" for j in lay.cmd_joints])
        tau = grid([f"tau_{j}" for j in lay.cmd_joints]) if mp.has_torque else None
        imu = grid(list(logs.IMU_COLS)) if mp.has_imu else None
        out.append(logs.Trajectory(f"{name}_{k:03d}", t - t[0], q, qd, cmd, tau, imu))
    return out


def _rotation(quat: np.ndarray) -> np.ndarray:
    """``[T, 3, 3]`` body-to-world rotations of unit quaternions ``[T, 4]`` (w x y z)."""
    w, x, y, z = quat.T
    return np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
                     np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
                     np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], 1)


def is_bag(path: pathlib.Path) -> bool:
    return path.is_dir() or path.suffix in (".mcap", ".db3", ".bag")


def run(mapping: str | os.PathLike, files: list[str | os.PathLike], out: str | os.PathLike,
        log=print) -> pathlib.Path:
    """Imports ``files`` (bags or CSVs) with ``mapping`` into the log folder ``out``."""
    mp = load_mapping(mapping)
    if not files:
        raise LogError("no recordings to import")
    trajs, notes = [], []
    for f in map(pathlib.Path, files):
        if not f.exists():
            raise LogError(f"{f}: no such file")
        streams = read_bag(f, mp) if is_bag(f) else read_table(f, mp)
        got = to_trajectories(streams, mp, re.sub(r"\W", "_", f.stem or f.name))
        if not got:
            raise LogError(f"{f}: no stretch of 3 control periods ({mp.sm.robot.ctrl_dt} s) that every "
                           "source covers")
        log(f"{f}: {len(got)} trajectories, {sum(len(tr.t) for tr in got)} samples")
        trajs += got
        notes.append(f.name)
    stale = sorted({p.name for p in pathlib.Path(out).glob("*.csv")} - {f"{tr.name}.csv" for tr in trajs})
    if stale:  # the reader would take them for trajectories of this import
        raise LogError(f"{out}: holds other trajectory files {stale[:4]}; import into a fresh folder")
    return logs.write(out, mp.sm, trajs, notes=f"imported by stride gap import with {mp.path.name} "
                                                f"from {', '.join(notes)}")
