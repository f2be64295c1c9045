"""experiments/trained_seeds.py: closed-loop rows of several trained seeds gathered per model kind."""

import json
import math

import pytest


def _row(scenario, model, vel, fell=False, run="", ms=10.0):
    return dict(scenario=scenario, model=model, run=run, vel_rmse=vel, fell=fell, ms_per_step=ms)


def test_kind_and_seed_read_the_run_folder_first_then_the_name(experiment):
    mod = experiment("trained_seeds")
    assert mod.kind_and_seed(_row("push", "stride", 0.1, run="/x/stride-s0")) == ("stride", 0)
    assert mod.kind_and_seed(_row("push", "stride_s2", 0.1, run="/x/stride-s2")) == ("stride", 2)
    # the run's folder wins over a name that says otherwise; a merged name's @part is dropped
    assert mod.kind_and_seed(_row("push", "onn_s1@p", 0.1, run="/x/onn-s4")) == ("onn", 4)
    assert mod.kind_and_seed(_row("push", "delan_s3", 0.1)) == ("delan", 3)
    assert mod.kind_and_seed(_row("push", "policy", 0.1)) == ("policy", 0)


def test_gather_keeps_each_seed_and_leaves_falls_out_of_the_mean(experiment):
    mod = experiment("trained_seeds")
    rows = [_row("push", "stride", 0.10, run="r/stride-s0"),
            _row("push", "stride_s1", 0.30, fell=True, run="r/stride-s1"),
            _row("push", "stride_s2", 0.14, run="r/stride-s2"),
            _row("rough", "onn_s1", 0.5, fell=True, run="r/onn-s1")]
    got = {(g["scenario"], g["model"]): g for g in mod.gather(rows)}
    g = got["push", "stride"]
    assert g["seeds"] == [0, 1, 2] and g["fell"] == [False, True, False]
    assert g["vel_rmse_mean"] == pytest.approx(0.12) and g["vel_rmse_worst"] == pytest.approx(0.14)
    assert math.isnan(got["rough", "onn"]["vel_rmse_mean"])  # no seed stayed up
    with pytest.raises(ValueError, match="two rows of stride seed 0"):
        mod.gather(rows + [_row("push", "stride@other", 0.2, run="q/stride-s0")])


def test_planner_draws_of_one_trained_seed_are_its_episodes(experiment):
    """Rows of ``--episodes N`` (the row's ``seed``: the planner's draw): each trained seed's
    RMSE is the mean of its draws that stayed up, its falls counted; the group's mean and worst
    run over every upright episode; the same draw twice is an error."""
    mod = experiment("trained_seeds")
    rows = [dict(_row("lowf", "stride", v, fell=f, run="r/stride-s0"), seed=d)
            for d, v, f in ((0, 0.50, True), (1, 0.06, False), (2, 0.08, False))]
    rows += [dict(_row("lowf", "stride_s1", 0.55, fell=True, run="r/stride-s1"), seed=d)
             for d in (0, 1)]
    (g,) = mod.gather(rows)
    assert g["seeds"] == [0, 1] and g["draws"] == [3, 2] and g["falls"] == [1, 2]
    assert g["vel_rmse"] == pytest.approx([0.07, 0.55]) and g["fell"] == [False, True]
    assert g["vel_rmse_mean"] == pytest.approx(0.07) and g["vel_rmse_worst"] == pytest.approx(0.08)
    assert len(g["episodes"]) == 5
    line = mod.table([g], {})[2]
    assert "| 0.070 (1/3 fell) / 0.550 (2/2 fell) | 0.070 | 0.080 | 3/5 |" in line
    with pytest.raises(ValueError, match="two rows of stride seed 0 at planner seed 2"):
        mod.gather(rows + [dict(_row("lowf", "stride@b", 0.1, run="q/stride-s0"), seed=2)])


def test_the_script_writes_table_json_and_figure(tmp_path, experiment):
    mod = experiment("trained_seeds")
    rows = [_row("push", "stride", 0.10, run="r/stride-s0"),
            _row("push", "stride_s1", 0.12, run="r/stride-s1"),
            _row("push", "onn", 0.2, run="r/onn-s0")]
    (tmp_path / "part").mkdir()
    (tmp_path / "part" / "closed_loop.json").write_text(json.dumps(dict(env={}, rows=rows)))
    ref = [dict(_row("push", "policy", 0.13), part="a")]
    (tmp_path / "ref.json").write_text(json.dumps(dict(rows=ref)))
    out = tmp_path / "o" / "seeds"
    assert mod.main([str(tmp_path / "part"), "--out", str(out), "--reference",
                     str(tmp_path / "ref.json"), "--ref", "policy=policy@a"]) == 0
    md = out.with_suffix(".md").read_text()
    assert "| push | stride | 0, 1 | 0.100 / 0.120 | 0.110 | 0.120 | 0/2 |" in md
    assert md.rstrip().endswith("| 0.130 |")  # the policy's row beside ONN's
    assert json.loads(out.with_suffix(".json").read_text())["groups"][1]["model"] == "onn"
    assert out.with_suffix(".png").stat().st_size > 0
    with pytest.raises(SystemExit, match="no such closed-loop table"):
        mod.main([str(tmp_path / "part"), "--out", str(out), "--reference",
                  str(tmp_path / "missing.json"), "--ref", "policy=policy"])
    with pytest.raises(SystemExit, match="expected LABEL=MODEL"):
        mod.main([str(tmp_path / "part"), "--out", str(out), "--reference",
                  str(tmp_path / "ref.json"), "--ref", "policy"])
    with pytest.raises(SystemExit, match="no row of 'oracle'"):
        mod.main([str(tmp_path / "part"), "--out", str(out), "--reference",
                  str(tmp_path / "ref.json"), "--ref", "oracle=oracle"])
