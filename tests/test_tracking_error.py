"""experiments/tracking_error.py: a planner's velocity error split into a steady offset and the
variance about it, from saved closed-loop traces."""

import json

import numpy as np
import pytest

from stride_jax.control.episode import tracked


def _trace(path, offset, sway, n=200, dt=0.02, change_at=100, fall_at=None):
    """A trace whose velocity is the command plus ``offset`` plus a lateral sine of amplitude
    ``sway``, the command stepping once at ``change_at``."""
    t = dt * np.arange(n, dtype=np.float32)
    command = np.zeros((n, 3), np.float32)
    command[:, 0] = 0.5
    command[change_at:, 0] = 0.8
    v = command.copy()
    v[:, :2] += offset
    v[:, 1] += sway * np.sin(2 * np.pi * 2.0 * t)
    fallen = np.zeros(n, bool)
    if fall_at is not None:
        fallen[fall_at:] = True
    np.savez(path, t=t, command=command, v_base=v, fallen=fallen)


def test_scored_steps_follow_the_settle_time_and_the_fall():
    import types
    t = 0.02 * np.arange(10)
    command = np.zeros((10, 3))
    command[4:, 0] = 1.0
    fallen = np.zeros(10, bool)
    fallen[8:] = True
    use = tracked(types.SimpleNamespace(t=t, command=command, fallen=fallen), settle_s=0.03)
    assert use.tolist() == [False, False, True, True, False, False, True, True, False, False]


def test_offsets_and_variance_add_up_to_the_mean_square_error(tmp_path, experiment):
    mod = experiment("tracking_error")
    for name, off in (("stride", -0.01), ("stride_s1", -0.03), ("delan", 0.0)):
        _trace(tmp_path / f"trace_changes_{name}.npz", np.array([off, 0.0]), sway=0.04)
    _trace(tmp_path / "trace_changes_stride_seed1.npz", np.array([-0.01, 0.0]), sway=0.04)
    _trace(tmp_path / "trace_changes_stride_shared.npz", np.array([1.0, 0.0]), sway=0.0)  # not stride's
    _trace(tmp_path / "trace_push_stride.npz", np.array([1.0, 0.0]), sway=0.0)  # another scenario
    r = mod.decompose(tmp_path, "changes", "stride")
    assert r["seeds"] == [0, 1] and r["episodes"] == 3
    # seed 0 twice (two draws) at -0.01, seed 1 at -0.03, equal steps each: (-0.01 - 0.01 - 0.03) / 3
    assert r["offset_x"] == pytest.approx(-0.05 / 3, abs=1e-6)
    assert r["seed_offset_x"] == pytest.approx([-0.01, -0.03], abs=1e-6)
    assert r["offset_y"] == pytest.approx(0.0, abs=2e-3)
    assert r["var_y"] == pytest.approx(0.04 ** 2 / 2, rel=0.1)  # a sine's variance
    assert r["mse"] == pytest.approx(r["offset_x"] ** 2 + r["offset_y"] ** 2 + r["var_x"]
                                     + r["var_y"], rel=1e-5)
    # the steps within 0.5 s of a change are not scored: 200 - 25 - 25 per trace
    assert r["steps"] == 3 * 150


def test_the_script_writes_table_json_and_figure_and_names_bad_picks(tmp_path, experiment):
    mod = experiment("tracking_error")
    _trace(tmp_path / "trace_changes_stride.npz", np.array([-0.01, 0.0]), sway=0.04)
    _trace(tmp_path / "trace_changes_delan.npz", np.array([0.0, 0.0]), sway=0.04, fall_at=60)
    out = tmp_path / "out" / "err"
    assert mod.main(["--scenario", "changes", f"STRIDE={tmp_path}:stride",
                     f"DeLaN={tmp_path}:delan", "--out", str(out)]) == 0
    rows = json.loads(out.with_suffix(".json").read_text())["rows"]
    assert rows["DeLaN"]["steps"] == 60 - 25  # up to the fall
    assert "| STRIDE | 1 | 150 |" in out.with_suffix(".md").read_text()
    assert out.with_suffix(".png").stat().st_size > 1000
    with pytest.raises(SystemExit, match="no trace_changes_onn"):
        mod.main(["--scenario", "changes", f"ONN={tmp_path}:onn", "--out", str(out)])
    with pytest.raises(SystemExit, match="expected LABEL=FOLDER:MODEL"):
        mod.main(["--scenario", "changes", str(tmp_path), "--out", str(out)])
