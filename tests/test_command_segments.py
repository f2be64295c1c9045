"""experiments/command_segments.py: a closed loop's tracking error per stretch of constant command."""

import json

import numpy as np
import pytest

DT = 0.02
SCHEDULE = ((0.0, 1.0, 0.0), (0.3, 0.4, 0.0), (0.0, 0.0, 0.0))  # 1 s each


def _trace(path, offsets, fall_at=None):
    """A 3 s trace whose forward speed misses each segment's command by ``offsets[i]``."""
    n = int(round(3.0 / DT))
    t = DT * np.arange(1, n + 1)
    seg = np.minimum((np.arange(n) * DT // 1.0).astype(int), 2)
    command = np.asarray(SCHEDULE, np.float32)[seg]
    v = np.zeros((n, 3), np.float32)
    v[:, :2] = command[:, :2]
    v[:, 0] += np.asarray(offsets, np.float32)[seg]
    fallen = np.zeros(n, bool) if fall_at is None else t >= fall_at
    np.savez(path, t=t, command=command, v_base=v, w_base=np.zeros((n, 3)), fallen=fallen)
    return path


def test_each_segment_scores_its_own_error_after_the_settling_time(experiment, tmp_path):
    mod = experiment("command_segments")
    a = _trace(tmp_path / "trace_a.npz", [0.1, 0.2, 0.4])
    b = _trace(tmp_path / "trace_b.npz", [0.3, 0.2, 0.0])
    got = mod.table({"x": [str(a), str(b)]})
    assert [s["command"] for s in got["segments"]] == [list(c) for c in np.float32(SCHEDULE).tolist()]
    assert [s["start"] for s in got["segments"]] == pytest.approx([DT, 1.0 + DT, 2.0 + DT])
    row = got["rows"][0]
    assert row["segments"] == pytest.approx([0.2, 0.2, 0.2], abs=1e-6)  # per segment, mean of draws
    # the whole episode's: the closed loop's own RMSE over the scored steps, mean over the draws
    assert row["whole"] == pytest.approx((np.sqrt((0.01 + 0.04 + 0.16) / 3)
                                          + np.sqrt((0.09 + 0.04) / 3)) / 2, abs=1e-6)
    assert row["fell"] == 0


def test_a_fall_leaves_its_steps_unscored_and_is_counted(experiment, tmp_path):
    mod = experiment("command_segments")
    a = _trace(tmp_path / "trace_a.npz", [0.1, 0.5, 0.5], fall_at=1.4)
    row = mod.table({"x": [str(a)]})["rows"][0]
    assert row["segments"][0] == pytest.approx(0.1, abs=1e-6)
    assert np.isnan(row["segments"][2]) and row["fell"] == 1


def test_traces_of_other_schedules_or_none_are_clear_errors(experiment, tmp_path):
    mod = experiment("command_segments")
    a = _trace(tmp_path / "trace_a.npz", [0.1, 0.2, 0.4])
    other = tmp_path / "trace_b.npz"
    _trace(other, [0.1, 0.2, 0.4])
    with np.load(other) as d:
        arrays = dict(d)
    arrays["command"][-10:, 0] = 0.5  # a fourth piece
    np.savez(other, **arrays)
    with pytest.raises(SystemExit, match="schedule differs"):
        mod.table({"x": [str(a), str(other)]})
    with pytest.raises(SystemExit, match="no trace matches"):
        mod.table({"x": []})


def test_the_script_writes_its_table_and_command(experiment, tmp_path):
    mod = experiment("command_segments")
    _trace(tmp_path / "trace_a.npz", [0.1, 0.2, 0.4])
    out = tmp_path / "seg"
    assert mod.main([f"policy={tmp_path}/trace_*.npz", "--out", str(out)]) == 0
    md = (tmp_path / "seg.md").read_text()
    assert "| policy | 1 | 0.100 | 0.200 | 0.400 |" in md
    assert json.loads((tmp_path / "seg.json").read_text())["command"].startswith(
        "python experiments/command_segments.py")
