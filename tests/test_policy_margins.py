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

