"""experiments/probes/policy_margins.py: policy_noise.py's outputs gathered into one table."""

import json

import pytest


def _write(folder, name, noise, falls, ar=0.9, draws=64):
    rows = [dict(noise=n, draws=draws, falls=f, fall_s=[], vx_at_1s=0.5) for n, f in zip(noise, falls)]
    (folder / f"{name}.json").write_text(json.dumps(dict(command=f"cmd {name}", scenario="x", ar=ar,
                                                         rows=rows)))


def test_a_row_per_policy_a_column_per_scenario_at_the_levels_asked(experiment, tmp_path):
    mod = experiment("probes/policy_margins")
    _write(tmp_path, "g1_soft_cpu64_slope", [0.0, 0.001, 0.003, 0.01], [0, 12, 15, 9])
    _write(tmp_path, "g1_tilt_cpu64_slope", [0.001, 0.01], [0, 3])
    _write(tmp_path, "g1_tilt_cpu64_softlr", [0.001], [11])
    _write(tmp_path, "g1_tilt_64_softlr", [0.0], [11])  # another tag: left out
    _write(tmp_path, "go1_tilt_cpu64_slope", [0.001, 0.01], [5, 5])  # another robot: left out
    data = mod.gather(tmp_path, "g1", "cpu64")
    assert set(data) == {"slope", "softlr"} and set(data["slope"]) == {"soft", "tilt"}
    scenarios, ar, md = mod.table(data, [0.001, 0.01])
    assert scenarios == ["soft", "tilt"] and ar == 0.9
    assert "| slope | 12 / 9 of 64 | 0 / 3 of 64 |" in md  # the levels asked, not the file's first
    assert "| softlr | - | 11 / ? of 64 |" in md  # not run there; a level that file lacks
    _write(tmp_path, "g1_push_cpu64_slope", [0.001, 0.01], [0, 0], ar=0.0)
    with pytest.raises(SystemExit, match="AR"):
        mod.table(mod.gather(tmp_path, "g1", "cpu64"), [0.001])
    with pytest.raises(SystemExit, match="no g1_\\*_gpu9_\\*.json"):
        mod.gather(tmp_path, "g1", "gpu9")


def test_policy_noise_counts_falls_and_creeps_and_reads_the_last_second_of_those_that_stood(
        experiment):
    """policy_noise.py's per-draw statistics on hand-made traces: a steady draw, one that runs
    past the command and stands, one that runs away and falls."""
    import numpy as np

    mod = experiment("probes/policy_noise")
    T = 150  # 3 s at 50 Hz
    t = np.arange(T) * 0.02
    command = np.zeros((3, T, 3))
    command[..., 0] = 1.0
    v = np.zeros((3, T, 3))
    v[0, :, 0] = 1.0  # steady at the command
    v[1, :, 0] = np.where(t >= 1.5, 1.4, 1.0)  # 0.4 past from 1.5 s, upright
    v[2, :, 0] = np.where(t > 1.5, 1.2, 1.0)  # 0.2 past from 1.5 s ...
    fallen = np.zeros((3, T), bool)
    fallen[2, t >= 2.5] = True  # ... and falls at 2.5 s, lying at 3 m/s
    v[2, t >= 2.5, 0] = 3.0
    s = mod.draw_stats(t, fallen, v, command, over=0.25)
    assert s["falls"] == 1 and s["fall_s"] == [t[t >= 2.5][0]]
    assert s["overspeed"] == 1  # draw 1 alone: draw 2's 3 m/s came after its fall
    # the median of the two that stood (1.0, 1.4), not the fallen draw's 3.0
    assert s["vx_last_s"] == pytest.approx(1.2)
    assert mod.draw_stats(t, fallen, v, command, over=0.1)["overspeed"] == 2
    assert mod.draw_stats(t, np.ones_like(fallen), v, command, over=0.25)["vx_last_s"] is None
