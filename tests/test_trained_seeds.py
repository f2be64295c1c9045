"""experiments/trained_seeds.py: closed-loop rows of several trained seeds gathered per model kind."""

import json
import math

import numpy as np
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


def test_seed_means_drop_or_keep_the_seeds_whose_every_draw_fell():
    """The report's comparison leaves out a seed that never stayed up; the table shows it with
    its error until the falls; non-finite errors count nowhere; another choice is refused."""
    from stride_paper.seeds import seed_means
    rows = [_row("push", "stride", 0.1, run="r/stride-s0"),
            _row("push", "stride", 0.3, fell=True, run="r/stride-s0"),
            _row("push", "stride_s1", 0.5, fell=True, run="r/stride-s1"),
            _row("push", "stride_s1", 0.7, fell=True, run="r/stride-s1"),
            _row("push", "stride_s2", float("nan"), run="r/stride-s2")]
    assert seed_means(rows) == {0: pytest.approx(0.1)}
    assert seed_means(rows, fallen="all") == {0: pytest.approx(0.1), 1: pytest.approx(0.6)}
    with pytest.raises(ValueError, match="fallen must be"):
        seed_means(rows, fallen="keep")


def test_a_headline_takes_whole_parts_or_some_models_or_scenarios_of_a_part():
    """``PART`` takes every row of the part, ``PART:MODEL+MODEL`` those models' (by merged name or
    the name before ``@part``), ``PART/SCENARIO+SCENARIO`` those scenarios', ``PART:M/S`` both;
    a part named whole and in part is taken whole; no headline: None."""
    from stride_paper.seeds import headline_picks, in_headline
    rows = [dict(model="policy@old", part="old"), dict(model="stride@old", part="old"),
            dict(model="onn", part="old"), dict(model="stride", part="new"),
            dict(model="stride", part="other")]
    rows = [dict(r, scenario="slope") for r in rows]
    picks = headline_picks({"headline": {"parts": ["new", "old:policy+onn"]}})
    assert picks == {"new": None, "old": frozenset({(frozenset({"policy", "onn"}), None)})}
    assert [in_headline(r, picks) for r in rows] == [True, False, True, True, False]
    assert headline_picks({"headline": {"parts": ["old:policy", "old"]}}) == {"old": None}
    assert headline_picks({"headline": {"parts": ["old", "old:policy"]}}) == {"old": None}
    two = headline_picks({"headline": {"parts": ["old:policy", "old:onn"]}})
    assert [in_headline(r, two) for r in rows[:3]] == [True, False, True]
    assert headline_picks({"rows": []}) is None
    # scenarios: a part's other scenarios left out, alone or with models
    mixed = rows + [dict(model="stride", part="new", scenario="changes"),
                    dict(model="onn", part="old", scenario="changes")]
    for entries, want in ((["new/slope"], [False, False, False, True, False, False, False]),
                          (["new/changes+slope", "old:onn/changes"],
                           [False, False, False, True, False, True, True]),
                          (["old/changes", "old:policy"],
                           [True, False, False, False, False, False, True])):
        picks = headline_picks({"headline": {"parts": entries}})
        assert [in_headline(r, picks) for r in mixed] == want, entries
    # the reading refuses what the merge refuses: a ':' or '/' with no names would take all
    for bad in ("old:", "old/", "old:onn/", ":onn"):
        with pytest.raises(ValueError, match="names no|no part"):
            headline_picks({"headline": {"parts": [bad]}})


def test_at_most_orders_by_fall_rate_then_error():
    """Falling less often wins whatever the upright error; equal rates (1 of 3 and 2 of 6) go to
    the error; no upright draw (NaN) loses to any error."""
    from stride_paper.seeds import at_most, fall_rates_differ
    assert at_most(0, 3, 0.9, 1, 3, 0.1) and not at_most(1, 3, 0.1, 0, 3, 0.9)
    assert not fall_rates_differ(1, 3, 2, 6) and fall_rates_differ(1, 3, 1, 6)
    assert at_most(1, 3, 0.2, 2, 6, 0.2) and not at_most(1, 3, 0.21, 2, 6, 0.2)
    assert at_most(3, 3, math.nan, 3, 3, math.nan) and not at_most(3, 3, math.nan, 3, 3, 0.5)
    # cells (a kind's rows in a scenario) the same way; a missing cell: no verdict
    from stride_paper.seeds import cell_at_most
    cell = lambda falls, n, err: dict(falls=falls, episodes=n, vel_rmse=err)  # noqa: E731
    assert cell_at_most(cell(0, 3, 0.9), cell(1, 3, 0.1)) is True
    assert cell_at_most(cell(1, 3, 0.21), cell(2, 6, 0.2)) is False
    assert cell_at_most(None, cell(0, 3, 0.1)) is None and cell_at_most(cell(0, 3, 0.1), None) is None


def test_planner_draws_of_one_trained_seed_are_its_episodes(experiment):
    """Rows of ``--episodes N`` (the row's ``seed``: the planner's draw): each trained seed's
    RMSE is the mean of its draws that stayed up, its falls counted; the group's mean and worst
    run over every upright episode; the same draw twice is an error."""
    mod = experiment("trained_seeds")
    rows = [dict(_row("lowf", "stride", v, fell=f, run="r/stride-s0"), seed=d, side_by_side=3)
            for d, v, f in ((0, 0.50, True), (1, 0.06, False), (2, 0.08, False))]
    rows += [dict(_row("lowf", "stride_s1", 0.55, fell=True, run="r/stride-s1"), seed=d)
             for d in (0, 1)]
    (g,) = mod.gather(rows)
    assert g["seeds"] == [0, 1] and g["draws"] == [3, 2] and g["falls"] == [1, 2]
    assert g["vel_rmse"] == pytest.approx([0.07, 0.55]) and g["fell"] == [False, True]
    assert g["vel_rmse_mean"] == pytest.approx(0.07) and g["vel_rmse_worst"] == pytest.approx(0.08)
    assert len(g["episodes"]) == 5
    lines = mod.table([g], {})
    assert "| 0.070 (1/3 fell) / 0.550 (2/2 fell) | 0.070 | 0.080 | 3/5 |" in lines[2]
    assert "(3 together) |" in lines[2]  # the step's wall time is the three draws' together
    # no versus column and no references: header, rule and row have the same columns
    assert len({line.count("|") for line in lines}) == 1 and not lines[0].endswith("|  |")
    with pytest.raises(ValueError, match="two rows of stride seed 0 at planner seed 2"):
        mod.gather(rows + [dict(_row("lowf", "stride@b", 0.1, run="q/stride-s0"), seed=2)])


def test_versus_gives_the_difference_of_means_with_welchs_interval(experiment):
    """Against STRIDE over upright trained seeds: the difference of the means and Welch's 90%
    interval (checked against scipy's own Welch test: the interval excludes 0 exactly when its
    two-sided p is below 0.10); too few upright seeds, or no STRIDE group, give None."""
    from scipy import stats
    mod = experiment("trained_seeds")
    st, de, on = [0.10, 0.12, 0.11], [0.20, 0.25, 0.18], [0.11, 0.13, 0.10]
    rows = [_row("push", "stride" + (f"_s{i}" if i else ""), v) for i, v in enumerate(st)]
    rows += [_row("push", "delan" + (f"_s{i}" if i else ""), v) for i, v in enumerate(de)]
    rows += [_row("push", "onn" + (f"_s{i}" if i else ""), v) for i, v in enumerate(on)]
    rows += [_row("push", f"policy_s{i}" if i else "policy", 0.3, fell=i > 0) for i in range(3)]
    rows += [_row("rough", "onn", 0.2), _row("rough", "onn_s1", 0.3)]
    got = {(g["scenario"], g["model"]): g["vs"] for g in mod.versus(mod.gather(rows))}
    assert got["push", "stride"] is None and got["rough", "onn"] is None
    assert got["push", "policy"] is None  # one seed stayed up
    for kind, vals in (("delan", de), ("onn", on)):
        v = got["push", kind]
        assert v["diff"] == pytest.approx(np.mean(vals) - np.mean(st))
        p = stats.ttest_ind(vals, st, equal_var=False).pvalue
        assert (v["lo"] > 0 or v["hi"] < 0) == (p < 0.10)
        assert v["lo"] < v["diff"] < v["hi"] and v["seeds"] == [3, 3]
    assert got["push", "delan"]["lo"] > 0  # told apart
    assert got["push", "onn"]["lo"] < 0 < got["push", "onn"]["hi"]  # not told apart
    line = mod.table(mod.versus(mod.gather(rows)), {})
    assert "minus stride (90% interval)" in line[0] and "| +0.100 [" in line[3]


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


def test_a_tables_variant_keeps_its_rows_apart_from_the_same_models_other_planner(tmp_path,
                                                                                   experiment):
    """The same trained models planned by two planners (e.g. mean-only and risk-aware): given
    as PATH and VARIANT=PATH, their rows are two kinds, not a clash of the same seed twice."""
    mod = experiment("trained_seeds")
    for part, vel in (("mean", 0.10), ("risk", 0.20)):
        rows = [_row("push", "stride", vel, run="r/stride-s0"),
                _row("push", "stride_s1", vel + 0.02, run="r/stride-s1")]
        (tmp_path / part).mkdir()
        (tmp_path / part / "closed_loop.json").write_text(json.dumps(dict(rows=rows)))
    out = tmp_path / "seeds"
    with pytest.raises(ValueError, match="two rows of stride seed 0"):
        mod.main([str(tmp_path / "mean"), str(tmp_path / "risk"), "--out", str(out)])
    assert mod.main([str(tmp_path / "mean"), f"risk-aware={tmp_path / 'risk'}",
                     "--out", str(out)]) == 0
    groups = {g["model"]: g for g in json.loads(out.with_suffix(".json").read_text())["groups"]}
    assert set(groups) == {"stride", "stride (risk-aware)"}
    assert groups["stride (risk-aware)"]["vel_rmse_mean"] == pytest.approx(0.21)
    assert "| push | stride (risk-aware) |" in out.with_suffix(".md").read_text()
