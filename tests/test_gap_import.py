"""``stride gap import``: ROS 2 bags (MCAP storage, written here with rosbags), a Unitree-SDK-style
CSV, the mapping file, and the errors for bad mappings and bad recordings."""

import textwrap

import numpy as np
import pytest

from stride_jax.gap import importer, logs, real
from stride_jax.jobs import gap as cli
from stride_jax.sim import model

T0 = 1.7e9  # epoch seconds: the importer must not lose the milliseconds
# A Unitree-like command message (the bag embeds its definition) beside sensor_msgs/JointState.
MOTOR_CMD = "string name\nfloat64 q\nfloat64 kp\n"
LOW_CMD = "uint32 tick\ntest_msgs/MotorCmd[] motor_cmd\n"
MAPPING = """
split_gap_s = 0.5

[robot]
name = "arm2"
mjcf = "arm.xml"
actuators = "position"
kp = 20.0
kd = 1.0
control_period_s = 0.01

[joints]
shoulder = "j_sh"
elbow = "j_el"

[sources]
q = {topic = "/joint_states", field = "position[name={joint}]"}
qd = {topic = "/joint_states", field = "velocity[name={joint}]"}
tau = {topic = "/joint_states", field = "effort[name={joint}]"}
cmd = {topic = "/lowcmd", field = "motor_cmd[name={joint}].q"}
qd_elbow = {topic = "/joint_states", field = "velocity[name=j_el]", scale = -1.0}

[stamps]
"/joint_states" = "header.stamp"
"""


@pytest.fixture(scope="module")
def arm(tmp_path_factory, arm_mjcf):
    d = tmp_path_factory.mktemp("arm")
    arm_mjcf(d)
    (d / "map.toml").write_text(MAPPING)
    sm = model.load(str(d / "map.toml"))
    clean, _ = real.generate(sm, None, 2, 40, seed=3)
    return d, sm, clean


def _write_bag(path, clean, pause_s=1.0, storage="MCAP"):
    """The two trajectories one after the other (``pause_s`` apart): joint states stamped at the
    sample times but recorded 0-3 ms late, the elbow's velocity sign flipped and the joints listed
    in the other order; commands published 2 ms before each sample."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    store.register(get_types_from_msg(MOTOR_CMD, "test_msgs/msg/MotorCmd")
                   | get_types_from_msg(LOW_CMD, "test_msgs/msg/LowCmd"))
    JS, Hd, Tm = (store.types[n] for n in ("sensor_msgs/msg/JointState", "std_msgs/msg/Header",
                                           "builtin_interfaces/msg/Time"))
    Cmd, MCmd = store.types["test_msgs/msg/LowCmd"], store.types["test_msgs/msg/MotorCmd"]
    rng = np.random.default_rng(0)
    with Writer(path, version=9, storage_plugin=StoragePlugin[storage]) as w:
        cj = w.add_connection("/joint_states", JS.__msgtype__, typestore=store)
        cc = w.add_connection("/lowcmd", Cmd.__msgtype__, typestore=store)
        start = int(T0) * 10**9
        for tr in clean:
            for k, t in enumerate(tr.t):
                ns = start + int(round(t * 1e9))
                stamp = Tm(sec=ns // 10**9, nanosec=ns % 10**9)
                js = JS(header=Hd(stamp=stamp, frame_id=""), name=["j_el", "j_sh"],
                        position=tr.q[k, ::-1].copy(), velocity=tr.qd[k, ::-1] * [-1, 1],
                        effort=tr.tau[k, ::-1].copy())
                cmd = Cmd(tick=k, motor_cmd=[MCmd(name=n, q=float(tr.cmd[k, i]), kp=20.0)
                                             for i, n in enumerate(["j_sh", "j_el"])])
                w.write(cc, ns - 2_000_000, store.serialize_cdr(cmd, Cmd.__msgtype__))
                late = ns + int(rng.integers(0, 3_000_000))
                w.write(cj, late, store.serialize_cdr(js, JS.__msgtype__))
            start += int(round((tr.t[-1] + pause_s) * 1e9))
    return path


def _check(trajs, clean, atol=1e-9):
    assert len(trajs) == len(clean)
    for a, b in zip(trajs, clean):
        assert len(a.t) == len(b.t)
        np.testing.assert_allclose(a.t, b.t - b.t[0], atol=1e-6)
        for f in ("q", "qd", "cmd", "tau"):
            np.testing.assert_allclose(getattr(a, f), getattr(b, f), atol=atol, err_msg=f)


def test_bag_and_mcap_import_round_trip(arm, tmp_path):
    d, sm, clean = arm
    bag = _write_bag(tmp_path / "bag", clean)
    out = importer.run(d / "map.toml", [bag], tmp_path / "logs", log=lambda s: None)
    h, trajs = logs.read(out, sm)
    assert h.robot == "arm2" and h.has_torque and h.command_kind == "position"
    _check(trajs, clean)  # split on the pause, on the control grid, elbow sign restored
    # the same recording as a bare MCAP file, without the bag's metadata.yaml
    (mcap,) = bag.glob("*.mcap")
    _, trajs = logs.read(importer.run(d / "map.toml", [mcap], tmp_path / "logs2", log=lambda s: None), sm)
    _check(trajs, clean)


def test_unitree_style_csv_import(tmp_path):
    """Pendulum (torque control), time in microseconds, the encoder counting the other way round
    with an offset, one file = one trajectory."""
    sm = model.load("pendulum")
    clean, _ = real.generate(sm, None, 1, 50, seed=1)
    tr = clean[0]
    rows = ["tick,timestamp_us,mode,motor0_q,motor0_dq,motor0_tau_cmd,motor0_tau_est"]
    for k in range(len(tr.t)):
        rows.append(f"{k},{int(round(T0 * 1e6 + tr.t[k] * 1e6))},FOC,{-(tr.q[k, 0] - 0.5):.12g},"
                    f"{-tr.qd[k, 0]:.12g},{tr.cmd[k, 0]:.12g},{tr.tau[k, 0]:.12g}")
    (tmp_path / "run.csv").write_text("\n".join(rows) + "\n")
    (tmp_path / "map.toml").write_text(textwrap.dedent("""
        robot = "pendulum"
        [joints]
        hinge = 0
        [sources]
        time = {column = "timestamp_us", scale = 1e-6}
        q = {column = "motor{joint}_q", scale = -1.0, offset = 0.5}
        qd = {column = "motor{joint}_dq", scale = -1.0}
        cmd = {column = "motor{joint}_tau_cmd"}
        tau = {column = "motor{joint}_tau_est"}
        """))
    out = importer.run(tmp_path / "map.toml", [tmp_path / "run.csv"], tmp_path / "logs", log=lambda s: None)
    h, trajs = logs.read(out, sm)
    assert h.command_kind == "torque" and [t.name for t in trajs] == ["run_000"]
    _check(trajs, clean, atol=1e-6)


def test_bad_mappings_name_the_key(arm, tmp_path):
    d, _, _ = arm

    def bad(text, match):
        p = d / "bad.toml"
        p.write_text(text)
        with pytest.raises(importer.MappingError, match=match):
            importer.load_mapping(p)

    bad(MAPPING.replace('cmd = {topic = "/lowcmd", field = "motor_cmd[name={joint}].q"}\n', ""),
        r"bad.toml: no source for column\(s\) \['cmd_shoulder', 'cmd_elbow'\]")
    bad(MAPPING.replace("shoulder = \"j_sh\"", "wrist = \"j_sh\""), r"\[joints\] \['wrist'\] are not joints")
    bad(MAPPING.replace("[sources]", "[sources]\nqdd = {column = 'x'}"), r"sources \['qdd'\] are not columns")
    bad(MAPPING.replace("field = \"position[name={joint}]\"}", "field = \"position[{jont}]\"}"),
        r"sources.q_shoulder: cannot fill in 'position\[\{jont\}\]'")
    bad(MAPPING.replace("[sources]", "[sources]\nbase_pos = {topic = '/odom', field = 'x'}"),
        r"floating-base robots only")
    bad(MAPPING + "\n[oops]\n", r"unknown key\(s\) \['oops'\]")
    bad('robot = "walle"\n[sources]\n', r"bad.toml: robot: unknown robot 'walle'")
    bad(MAPPING.replace("kp = 20.0\n", ""), r"needs kp")


def test_bad_recordings_name_the_topic_field_or_column(arm, tmp_path):
    d, _, clean = arm
    bag = _write_bag(tmp_path / "bag", [clean[0]])
    for old, new, match in [
            ('"/lowcmd"', '"/low_cmd"', r"topic\(s\) \['/low_cmd'\] \(for \['cmd_shoulder'\]\) not in the bag"),
            ("motor_cmd[name={joint}].q", "motor_cmd[name={joint}].dq",
             r"topic '/lowcmd' \(test_msgs/msg/LowCmd\), field 'motor_cmd\[name=j_sh\].dq' for column "
             r"'cmd_shoulder': no field 'dq' in 'motor_cmd\[name=j_sh\]'"),
            ("position[name={joint}]", "position[name=j_{joint}]", r"no element \[name=j_j_sh\] in 'position'"),
            ("motor_cmd[name={joint}].q", "motor_cmd[name={joint}].name", r"'cmd_shoulder': not a number"),
            ("motor_cmd[name={joint}].q", "motor_cmd[9].q", r"'motor_cmd' has 2 elements, index 9 asked")]:
        (d / "bad.toml").write_text(MAPPING.replace(old, new))
        with pytest.raises(logs.LogError, match=match):
            importer.run(d / "bad.toml", [bag], tmp_path / "x", log=lambda s: None)
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap file at all")
    with pytest.raises(logs.LogError, match=r"junk.mcap: not a readable ROS bag"):
        importer.run(d / "map.toml", [junk], tmp_path / "x", log=lambda s: None)
    csv = tmp_path / "a.csv"
    csv.write_text("t,q\n0,1\n")
    with pytest.raises(importer.MappingError, match=r"a CSV needs sources.time"):
        importer.run(d / "map.toml", [csv], tmp_path / "x", log=lambda s: None)


def test_bad_csv_names_the_column_and_row(tmp_path):
    (tmp_path / "map.toml").write_text(textwrap.dedent("""
        robot = "pendulum"
        [sources]
        time = {column = "t"}
        q = {column = "q"}
        qd = {column = "qd"}
        cmd = {column = "u"}
        """))
    (tmp_path / "a.csv").write_text("t,q,qd\n0,0,0\n0.01,0,0\n0.02,0,0\n")
    with pytest.raises(logs.LogError, match=r"a.csv: no column\(s\) \['u'\]"):
        importer.run(tmp_path / "map.toml", [tmp_path / "a.csv"], tmp_path / "x", log=lambda s: None)
    (tmp_path / "a.csv").write_text("t,q,qd,u\n0,0,0,0\n0.01,0,oops,0\n0.02,0,0,0\n")
    with pytest.raises(logs.LogError, match=r"column 'qd' \(for 'qd_hinge'\), row 2 \(line 3\): not a number"):
        importer.run(tmp_path / "map.toml", [tmp_path / "a.csv"], tmp_path / "x", log=lambda s: None)
    (tmp_path / "a.csv").write_text("t,q,qd,u\n0,0,0,0\n0.01,0,0,0\n0.005,0,0,0\n")
    with pytest.raises(logs.LogError, match=r"column 't' \(time\), row 3 .*must increase"):
        importer.run(tmp_path / "map.toml", [tmp_path / "a.csv"], tmp_path / "x", log=lambda s: None)


def test_cli_import(arm, tmp_path, capsys):
    """From a bag in ROS 2 Humble's default storage (SQLite, .db3)."""
    d, sm, clean = arm
    bag = _write_bag(tmp_path / "bag", clean, storage="SQLITE3")
    assert list(bag.glob("*.db3"))
    assert cli.main(["import", "--mapping", str(d / "map.toml"), "--out", str(tmp_path / "logs"),
                     str(bag)]) == 0
    assert len(logs.read(tmp_path / "logs", sm)[1]) == 2
    assert cli.main(["import", "--mapping", str(d / "map.toml"), "--out", str(tmp_path / "l2"),
                     str(tmp_path / "nothing.mcap")]) == 2
    assert "nothing.mcap: no such file" in capsys.readouterr().err
    (tmp_path / "logs" / "old_run.csv").write_text("time\n")
    assert cli.main(["import", "--mapping", str(d / "map.toml"), "--out", str(tmp_path / "logs"),
                     str(bag)]) == 2
    assert "holds other trajectory files ['old_run.csv']" in capsys.readouterr().err


def test_floating_base_from_csv_with_body_frame_velocity(tmp_path):
    """A free body with one flap: base pose and a body-frame linear velocity (as in
    nav_msgs/Odometry) on a 20 ms grid, recorded every 10 ms; the log holds it in the world frame."""
    (tmp_path / "box.xml").write_text("""<mujoco><option timestep="0.005"/><worldbody>
      <body name="torso" pos="0 0 0.5"><freejoint/><geom type="box" size="0.1 0.1 0.05" mass="2"/>
      <body name="flap"><joint name="flap" type="hinge" axis="0 1 0"/>
      <geom type="capsule" fromto="0 0 0 0.2 0 0" size="0.02" mass="0.1"/></body></body>
      </worldbody><actuator><position joint="flap" kp="5" ctrlrange="-1 1"/></actuator></mujoco>""")
    t = 0.01 * np.arange(41)
    yaw = 0.8 * t
    cols = {"t": t, "flap_q": np.sin(t), "flap_dq": np.cos(t), "flap_cmd": 0.5 + 0 * t,
            "x": t, "y": 0 * t, "z": 0.5 + 0 * t, "qw": np.cos(yaw / 2), "qx": 0 * t, "qy": 0 * t,
            "qz": np.sin(yaw / 2), "vx": 1 + 0 * t, "vy": 0 * t, "vz": 0 * t, "wx": 0 * t,
            "wy": 0 * t, "wz": 0.8 + 0 * t}
    (tmp_path / "run.csv").write_text(",".join(cols) + "\n" + "\n".join(
        ",".join(f"{v[k]:.12g}" for v in cols.values()) for k in range(len(t))) + "\n")
    (tmp_path / "map.toml").write_text(textwrap.dedent("""
        base_linvel_frame = "body"
        [robot]
        mjcf = "box.xml"
        control_period_s = 0.02
        [sources]
        time = {column = "t"}
        q = {column = "flap_q"}
        qd = {column = "flap_dq"}
        cmd = {column = "flap_cmd"}
        base_pos = {column = "{axis}"}
        base_quat = {column = "q{axis}"}
        base_linvel = {column = "v{axis}"}
        base_angvel = {column = "w{axis}"}
        """))
    sm = model.load(str(tmp_path / "map.toml"))
    out = importer.run(tmp_path / "map.toml", [tmp_path / "run.csv"], tmp_path / "logs", log=lambda s: None)
    h, (tr,) = logs.read(out, sm)
    assert h.floating_base and h.robot == "box" and len(tr.t) == 21
    np.testing.assert_allclose(tr.q[:, 0], t[::2], atol=1e-9)
    yaw = 0.8 * t[::2]
    np.testing.assert_allclose(tr.q[:, 3:7], np.stack([np.cos(yaw / 2), 0 * yaw, 0 * yaw,
                                                        np.sin(yaw / 2)], 1), atol=1e-9)
    np.testing.assert_allclose(tr.qd[:, :2], np.stack([np.cos(yaw), np.sin(yaw)], 1), atol=1e-9)
    np.testing.assert_allclose(tr.q[:, 7], np.sin(t[::2]), atol=1e-9)


def test_mapping_examples_in_the_docs_parse(go1, tmp_path):
    import pathlib
    import re
    import tomllib

    from stride_jax.robots import mjcf

    doc = pathlib.Path(__file__).resolve().parents[1] / "docs" / "gap.md"
    go1_map, csv_map, panda = re.findall(r"```toml\n(.*?)```", doc.read_text(), re.S)
    (tmp_path / "go1.toml").write_text(go1_map)
    mp = importer.load_mapping(tmp_path / "go1.toml")
    assert mp.sm is go1 and mp.has_torque and mp.has_imu and mp.linvel_body
    assert mp.columns["q_FR_hip_joint"].scale == -1.0
    assert mp.columns["qd_RL_calf_joint"].field == "motor_state[11].dq"
    assert mp.columns["base_quat_w"].field == "pose.pose.orientation.w"
    assert mp.columns["imu_acc_z"].field == "imu_state.accelerometer[2]"
    (tmp_path / "csv.toml").write_text(csv_map)
    assert importer.load_mapping(tmp_path / "csv.toml").time.scale == 1e-6
    assert set(tomllib.loads(panda)["robot"]) <= mjcf.KEYS
