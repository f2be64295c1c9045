"""Any robot: a robot built from an MJCF file or a robot file, and the gap tool diagnosing it."""

import json

import numpy as np
import pytest

from stride_jax.gap import logs
from stride_jax.jobs import gap as cli
from stride_jax.robots import RobotError, get
from stride_jax.sim import model


def test_mjcf_with_its_own_actuators(tmp_path, arm_mjcf):
    servos = arm_mjcf(tmp_path, """<actuator>
      <position joint="shoulder" kp="30" kv="2" ctrlrange="-2 2"/>
      <position joint="elbow" kp="20" kv="1" ctrlrange="-2 2"/>
      <position joint="wrist" kp="5" ctrlrange="-2 2"/></actuator>""", "servos.xml", hand=True)
    r = get(str(servos))
    assert r.name == "servos" and r.joints == ("shoulder", "elbow", "wrist")
    assert r.kp == (30.0, 20.0, 5.0) and r.kd == (2.0, 1.0, 0.0) and not r.floating_base
    assert r.base_body == "hand" and r.ctrl_dt == pytest.approx(0.02)  # payload at the tool
    motors = arm_mjcf(tmp_path, """<actuator><motor joint="elbow" ctrlrange="-5 5"/>
      <motor joint="shoulder" ctrlrange="-5 5"/></actuator>""", "motors.xml", hand=True)
    r = get(str(motors))
    assert r.kp is None and r.joints == ("elbow", "shoulder")
    with pytest.raises(RobotError, match="no actuators; write a robot file"):
        get(str(arm_mjcf(tmp_path, hand=True)))
    mixed = arm_mjcf(tmp_path, """<actuator><motor joint="elbow" ctrlrange="-5 5"/>
      <position joint="shoulder" kp="3"/></actuator>""", "mixed.xml", hand=True)
    with pytest.raises(RobotError, match="all position servos or all motors"):
        get(str(mixed))


def test_robot_file_adds_actuators_and_welds(tmp_path, arm_mjcf):
    arm_mjcf(tmp_path, hand=True)
    f = tmp_path / "arm.toml"
    f.write_text('[robot]\nmjcf = "arm.xml"\nactuators = "motor"\ntorque_limit = {shoulder = 8, elbow = 4}\n'
                 'joints = ["shoulder", "elbow"]\nweld = ["wrist"]\ncontrol_period_s = 0.01\n')
    sm = model.load(str(f))
    assert sm.robot.name == "arm" and sm.robot.kp is None and sm.n_substeps == 5
    assert logs.layout(sm).joints == ("shoulder", "elbow")  # the wrist is welded: not logged
    np.testing.assert_allclose(sm.mj.actuator_ctrlrange, [[-8, 8], [-4, 4]])
    f.write_text('[robot]\nmjcf = "arm.xml"\nactuators = "motor"\njoints = ["shoulder"]\n')
    with pytest.raises(RobotError, match="needs torque_limit"):
        model.load(str(f))  # recompiled: the text changed
    f.write_text('[robot]\nmjcf = "arm.xml"\nactuators = "position"\nkp = 3\njoints = ["knee"]\n')
    with pytest.raises(RobotError, match=r"robot.joints \['knee'\]: not hinge or slide joints"):
        model.load(str(f))
    f.write_text('[robot]\nmjcf = "arm.xml"\nactuator = "position"\n')
    with pytest.raises(RobotError, match=r"unknown robot key\(s\) \['actuator'\]"):
        model.load(str(f))


def test_gap_simulate_and_diagnose_a_robot_file(tmp_path, capsys, arm_mjcf):
    """A 2-joint arm with position servos, only known as an MJCF plus a robot file: a planted
    joint damping is named (tiny preset, noise-free logs)."""
    arm_mjcf(tmp_path, hand=True)
    f = tmp_path / "arm.toml"
    f.write_text('[robot]\nname = "arm"\nmjcf = "arm.xml"\nactuators = "position"\nkp = 20.0\n'
                 'kd = 1.0\nweld = ["wrist"]\ncontrol_period_s = 0.01\n')
    logs_dir, rep = tmp_path / "logs", tmp_path / "report"
    assert cli.main(["simulate", "--robot", str(f), "--out", str(logs_dir), "--effects",
                     '{"damping": 0.3}', "--trajectories", "5", "--steps", "100"]) == 0
    assert json.loads((logs_dir / "header.json").read_text())["robot"] == "arm"
    assert cli.main(["diagnose", "--robot", str(f), "--logs", str(logs_dir), "--out", str(rep),
                     "--preset", "tiny", "--residual.when", "never"]) == 0
    d = json.loads((rep / "diagnosis.json").read_text())
    assert d["verdict"]["verdict"] == "explained" and d["verdict"]["effects"][0] == "damping"
    assert cli.main(["diagnose", "--robot", str(tmp_path / "nope.toml"), "--logs", str(logs_dir),
                     "--out", str(rep)]) == 2
    assert "nope.toml': no such file" in capsys.readouterr().err


def test_welding_a_gripper_drops_its_tendon_equality_and_actuator(tmp_path):
    """Coupled fingers as in Menagerie's Panda: a fixed tendon over both, a joint equality and a
    tendon actuator; welding the fingers leaves the arm joint and its own servo."""
    (tmp_path / "grip.xml").write_text("""<mujoco><worldbody><body name="a" pos="0 0 1">
      <joint name="j1" axis="0 1 0"/><geom size="0.1" mass="1"/>
      <body name="f1"><joint name="finger_joint1" type="slide" axis="1 0 0" range="0 0.04"/>
      <geom size="0.01" mass="0.1"/></body>
      <body name="f2"><joint name="finger_joint2" type="slide" axis="-1 0 0" range="0 0.04"/>
      <geom size="0.01" mass="0.1"/></body></body></worldbody>
      <tendon><fixed name="split"><joint joint="finger_joint1" coef="0.5"/>
      <joint joint="finger_joint2" coef="0.5"/></fixed></tendon>
      <equality><joint joint1="finger_joint1" joint2="finger_joint2"/></equality>
      <actuator><general joint="j1" gainprm="10" biasprm="0 -10 -1" biastype="affine"/>
      <general tendon="split" ctrlrange="0 255" gainprm="0.0157" biasprm="0 -100 -10" biastype="affine"/>
      </actuator></mujoco>""")
    f = tmp_path / "grip.toml"
    f.write_text('[robot]\nmjcf = "grip.xml"\nweld = ["finger_joint1", "finger_joint2"]\n')
    sm = model.load(str(f))
    assert sm.robot.joints == ("j1",) and sm.robot.kp == (10.0,) and sm.robot.kd == (1.0,)
    assert (sm.mj.njnt, sm.mj.ntendon, sm.mj.neq, sm.mj.nu) == (1, 0, 0, 1)
    with pytest.raises(RobotError, match="only joint actuators"):
        model.load(str(tmp_path / "grip.xml"))
