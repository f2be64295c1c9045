"""experiments/speed_vs_error.py: a scenario's tracking error against the forward speed."""

import json

import pytest


def _row(model, vx, err, part="p", scenario="slope", **kw):
    return dict(model=model, scenario=scenario, part=part, mean_vx=vx, vel_rmse=err, fell=False,
                ms_per_step=1.0, **kw)


def test_models_ranked_by_speed_and_error_over_their_draws(experiment, tmp_path):
    """Each trained model is the mean of its draws; the correlation is over the learned models
    alone (the policy listed, not counted); rows outside the headline or scenario are left out."""
    mod = experiment("speed_vs_error")
    rows = [_row("stride", 1.00, 0.05, seed=0), _row("stride", 1.02, 0.07, seed=1),  # draws
            _row("stride_s1", 1.05, 0.09), _row("delan", 1.04, 0.08), _row("onn", 0.98, 0.04),
            _row("policy", 1.20, 0.01), _row("onn_s1", 0.50, 0.50, part="old"),
            _row("delan_s1", 0.50, 0.50, scenario="tilt")]
    table = dict(rows=rows, headline=dict(parts=["p"]))
    got = mod.speed_and_error(table, "slope")
    by = {(m["kind"], m["seed"]): m for m in got["models"]}
    assert set(by) == {("stride", 0), ("stride", 1), ("delan", 0), ("onn", 0), ("policy", 0)}
    assert by[("stride", 0)]["draws"] == 2 and by[("stride", 0)]["mean_vx"] == pytest.approx(1.01)
    assert got["spearman"] == pytest.approx(1.0)  # speed and error in the same order
    flipped = [dict(r, vel_rmse=1 - r["vel_rmse"]) for r in rows]
    flip = mod.speed_and_error(dict(table, rows=flipped), "slope")
    assert flip["spearman"] == pytest.approx(-1.0)
    (tmp_path / "t.json").write_text(json.dumps(table))
    out = mod.main([str(tmp_path / "t.json"), "--scenarios", "slope", "--out", str(tmp_path / "o")])
    assert out["slope"]["spearman"] == pytest.approx(1.0)
    assert "Spearman +1.00" in (tmp_path / "o.md").read_text()


def test_bad_input_is_named(experiment, tmp_path):
    mod = experiment("speed_vs_error")
    with pytest.raises(ValueError, match="no headline"):
        mod.speed_and_error(dict(rows=[_row("onn", 1.0, 0.1)]), "slope")
    with pytest.raises(ValueError, match="no headline rows of scenario 'rough'"):
        mod.speed_and_error(dict(rows=[_row("onn", 1.0, 0.1)], headline=dict(parts=["p"])), "rough")
    with pytest.raises(SystemExit, match="no such file"):
        mod.main([str(tmp_path / "none.json"), "--scenarios", "slope",
                  "--out", str(tmp_path / "o")])
