"""The gap tool's log format: round trip and validation errors."""

import json

import numpy as np
import pytest

from stride_jax.gap import logs, real
from stride_jax.sim import model


@pytest.fixture(scope="module")
def go1_logs(go1, tmp_path_factory):
    clean, _ = real.generate(go1, None, 2, 25, seed=0, min_steps=3)
    path = tmp_path_factory.mktemp("go1logs")
    logs.write(path, go1, clean)
    return path, clean


def test_round_trip_go1(go1, go1_logs):
    path, clean = go1_logs
    h, trajs = logs.read(path, go1)
    assert h.robot == "go1" and h.has_torque and h.has_imu and h.command_kind == "position"
    assert len(trajs) == len(clean)
    for a, b in zip(trajs, clean):
        np.testing.assert_allclose(a.q, b.q, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(a.qd, b.qd, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(a.cmd, b.cmd, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(a.tau, b.tau, rtol=1e-9, atol=1e-9)
        # on average over a trajectory the accelerometer sees gravity, body z up: about 9.8 m/s^2
        assert 7 < a.imu[:, 2].mean() < 13


def _rewrite(path, fn, out):
    """Copies a log folder to ``out`` with ``fn(lines)`` applied to the first CSV's lines."""
    out.mkdir()
    (out / "header.json").write_text((path / "header.json").read_text())
    csvs = sorted(path.glob("*.csv"))
    lines = csvs[0].read_text().splitlines()
    (out / csvs[0].name).write_text("\n".join(fn(lines)) + "\n")
    return out


def test_bad_logs_are_rejected_clearly(go1, go1_logs, tmp_path):
    path, _ = go1_logs
    name = sorted(path.glob("*.csv"))[0].name

    def drop_col(lines):
        cols = lines[0].split(",")
        k = cols.index("qd_FL_calf_joint")
        return [",".join(c for i, c in enumerate(ln.split(",")) if i != k) for ln in lines]

    with pytest.raises(logs.LogError, match=rf"{name}.*missing column.*qd_FL_calf_joint"):
        logs.read(_rewrite(path, drop_col, tmp_path / "a"), go1)

    def nan(lines):
        row = lines[5].split(",")
        row[3] = "nan"
        return lines[:5] + [",".join(row)] + lines[6:]

    col3 = (path / name).read_text().splitlines()[0].split(",")[3]
    with pytest.raises(logs.LogError, match=rf"column '{col3}', row 5 .*NaN"):
        logs.read(_rewrite(path, nan, tmp_path / "b"), go1)

    def swap_time(lines):
        return [lines[0], lines[1], lines[3], lines[2]] + lines[4:]

    with pytest.raises(logs.LogError, match=r"column 'time', row 3 .*increase"):
        logs.read(_rewrite(path, swap_time, tmp_path / "c"), go1)

    def text(lines):
        row = lines[2].split(",")
        row[-1] = "abc"
        return lines[:2] + [",".join(row)] + lines[3:]

    with pytest.raises(logs.LogError, match=r"not a number"):
        logs.read(_rewrite(path, text, tmp_path / "d"), go1)

    bad = tmp_path / "e"
    _rewrite(path, lambda ln: ln, bad)
    h = json.loads((bad / "header.json").read_text())
    h["joint_names"][0] = "FR_hip"
    (bad / "header.json").write_text(json.dumps(h))
    with pytest.raises(logs.LogError, match=r"joint-name mismatch.*FR_hip.*FR_hip_joint"):
        logs.read(bad, go1)
    with pytest.raises(logs.LogError, match="log is for robot 'go1'"):
        logs.read(path, model.load("pendulum"))
    with pytest.raises(logs.LogError, match="header.json: missing"):
        logs.read(tmp_path, go1)


def test_velocity_noise_round_trips_and_bad_levels_are_named(go1, go1_logs, tmp_path):
    """The header's optional ``velocity_noise``: per velocity channel (joints at once, one joint over
    that, the base's linear and angular velocity), written and read back as a per-dof level; absent,
    None; an unknown key, a bad level or an uncovered channel is an error naming it."""
    _, clean = go1_logs
    assert logs.velocity_std(logs.read(go1_logs[0], go1)[0], go1) is None
    spec = {"qd": 0.04, "qd_FR_calf_joint": 0.1, "base_linvel": 0.03, "base_angvel": 0.01}
    h, _ = logs.read(logs.write(tmp_path / "spec", go1, clean, velocity_noise=spec), go1)
    assert h.velocity_noise == spec
    std = logs.velocity_std(h, go1)
    lay = logs.layout(go1)
    calf = lay.vadr[lay.joints.index("FR_calf_joint")]
    np.testing.assert_allclose(std[:3], 0.03)
    np.testing.assert_allclose(std[3:6], 0.01)
    assert std[calf] == 0.1
    assert np.allclose(np.delete(std[6:], calf - 6), 0.04)
    for bad, match in (({"qd": 0.04, "base_linvel": 0.03, "base_angvel": 0.01, "qd_nope": 1.0}, r"\['qd_nope'\]"),
                       ({"qd": -0.04, "base_linvel": 0.03, "base_angvel": 0.01}, r"velocity_noise\['qd'\].*-0.04"),
                       ({"qd": float("nan"), "base_linvel": 0.03, "base_angvel": 0.01}, r"velocity_noise\['qd'\]"),
                       ({"qd": 0.04}, r"leaves \['base_linvel', 'base_angvel'\] uncovered")):
        with pytest.raises(logs.LogError, match=match):
            logs.write(tmp_path / "bad", go1, clean, velocity_noise=bad)
    # the reader checks a hand-edited header the same way, naming the file
    hdr = tmp_path / "spec" / "header.json"
    d = json.loads(hdr.read_text())
    hdr.write_text(json.dumps(d | {"velocity_noise": {"qd": 0.04}}))
    with pytest.raises(logs.LogError, match=r"header.json.*uncovered"):
        logs.read(tmp_path / "spec", go1)
    hdr.write_text(json.dumps(d | {"velocity_noise": [0.04]}))
    with pytest.raises(logs.LogError, match=r"header.json.*velocity_noise must be an object"):
        logs.read(tmp_path / "spec", go1)
