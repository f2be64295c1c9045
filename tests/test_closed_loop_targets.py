"""experiments/closed_loop_targets.py: issue 19's targets read off a merged table's headline."""

import json

import pytest


def _row(sc, model, v, part, fell=False, ms=80.0):
    return dict(scenario=sc, model=model, vel_rmse=v, fell=fell, ms_per_step=ms, part=part)


def _table():
    rows = [_row("soft", "policy", 0.05, "pol", ms=10.0), _row("rough", "policy", 0.09, "pol", ms=10.0)]
    for i, (rough, soft) in enumerate([(0.060, 0.051), (0.062, 0.052), (0.064, 0.053)]):
        sfx = f"_s{i}" if i else ""
        rows += [_row("rough", f"stride{sfx}@a", rough, "a"), _row("soft", f"stride{sfx}@a", soft, "a"),
                 _row("rough", f"onn{sfx}@b", rough + 0.01, "b", ms=15.0),
                 _row("soft", f"onn{sfx}@b", soft - 0.005, "b", ms=15.0)]
    # a row outside the headline is not read; the oracle's time is, from any part
    rows += [_row("rough", "stride@old", 0.5, "old", fell=True), _row("rough", "oracle", 0.07, "old", ms=500.0)]
    return {"parts": {p: {} for p in ("pol", "a", "b", "old")},
            "headline": {"parts": ["pol", "a", "b"]}, "rows": rows}


def test_targets_read_the_headline_seeds_and_the_oracle_time(experiment):
    mod = experiment("closed_loop_targets")
    r = mod.robot_targets(_table())
    cells = {c["scenario"]: c for c in r["cells"]}
    assert list(cells) == ["rough", "soft"]  # the issue's order, not the parts'
    assert cells["rough"]["stride"]["vel_rmse"] == pytest.approx(0.062)
    assert cells["rough"]["stride"]["seeds"] == 3 and cells["rough"]["stride"]["falls"] == 0
    assert cells["rough"]["stride_vs"] == {"policy": True, "delan": None, "onn": True}
    # soft: above the policy and ONN; ONN's three seeds sit 0.005 below STRIDE's: told apart
    assert cells["soft"]["stride_vs"]["policy"] is False and cells["soft"]["apart"]["onn"] is True
    assert cells["rough"]["time_ratio"] == pytest.approx(80.0 / 500.0)
    assert cells["soft"]["oracle_ms_from"] == "all scenarios"
    # the oracle's tracking: its headline rows only (the one in part "old" ran over another policy)
    assert cells["rough"]["oracle"] is None
    tab = _table()
    tab["rows"].append(_row("rough", "oracle@pol", 0.05, "pol", ms=600.0))
    cells = {c["scenario"]: c for c in mod.robot_targets(tab)["cells"]}
    assert cells["rough"]["oracle"]["vel_rmse"] == pytest.approx(0.05) and cells["soft"]["oracle"] is None
    assert cells["rough"]["oracle_ms"] == pytest.approx(550.0)  # the time: every oracle row of it
    md = mod.markdown({"go1": mod.robot_targets(tab)}, "cmd")
    assert "| rough | 0.090 | 0.062 | - | 0.072 | 0.050 | yes |" in md
    assert cells["rough"]["time_basis"] == "closed-loop step"  # rows without controller_ms
    # rows that timed their controllers: the ratio reads those (no world in them), where both
    # STRIDE's and the oracle's rows have them
    for row in tab["rows"]:
        if row["scenario"] == "rough" and row["model"].split("@")[0] in ("stride", "stride_s1",
                                                                       "stride_s2", "oracle"):
            row["controller_ms"] = 400.0 if row["model"].startswith("oracle") else 36.0
    cells = {c["scenario"]: c for c in mod.robot_targets(tab)["cells"]}
    assert cells["rough"]["time_basis"] == "controller"
    assert cells["rough"]["time_ratio"] == pytest.approx(36.0 / 400.0)
    assert cells["soft"]["time_basis"] == "closed-loop step"  # STRIDE's soft rows were not timed
    md = mod.markdown({"go1": mod.robot_targets(tab)}, "cmd")
    assert "| 36.0 c | 400 c | 0.09 |" in md and "c: the controllers' own time" in md
    t = r["targets"]
    assert t["no_falls"]["met"] and t["no_falls"]["stride_episodes"] == 6
    assert (t["at_most_policy"]["scenarios"], t["at_most_policy"]["of"]) == (1, 2)
    assert t["at_most_policy"]["met"] is False  # 1 of 2 is below 3 of 4
    assert t["at_most_baselines"]["met"] is False and t["time_fifth_of_oracle"]["met"]
    # per baseline, the scenarios STRIDE is at most it in (no DeLaN rows: none compared)
    assert t["at_most_baselines"]["onn"] == {"scenarios": 1, "of": 2}
    assert t["at_most_baselines"]["delan"] == {"scenarios": 0, "of": 0}
    assert "(1 of 2 comparisons; ONN's in 1 of 2 scenarios)" in mod.markdown({"go1": r}, "cmd")
    # a fall outweighs any error: STRIDE falling once on rough loses to the policy
    tab = _table()
    tab["rows"][2]["fell"] = True  # stride@a on rough (seed 0)
    r = mod.robot_targets(tab)
    rough = next(c for c in r["cells"] if c["scenario"] == "rough")
    assert rough["stride"]["falls"] == 1 and rough["stride_vs"]["policy"] is False
    assert r["targets"]["no_falls"]["met"] is False


def test_policy_rows_picked_from_other_parts_and_a_table_without_headline(experiment, tmp_path):
    mod = experiment("closed_loop_targets")
    tab = _table()
    tab["rows"] = [r for r in tab["rows"] if r["part"] != "pol"]
    tab["rows"].append(_row("soft", "policy", 0.06, "old"))
    r = mod.robot_targets(tab, "policy@old")
    soft = next(c for c in r["cells"] if c["scenario"] == "soft")
    assert soft["policy"]["vel_rmse"] == 0.06 and soft["stride_vs"]["policy"] is True
    assert next(c for c in r["cells"] if c["scenario"] == "rough")["policy"] is None
    # a headline taking some models of a part: the old part's policy row, not its fallen STRIDE
    tab["headline"]["parts"].append("old:policy")
    r = mod.robot_targets(tab)
    soft = next(c for c in r["cells"] if c["scenario"] == "soft")
    assert soft["policy"]["vel_rmse"] == 0.06 and r["targets"]["no_falls"]["met"]
    del tab["headline"]
    with pytest.raises(ValueError, match="no headline"):
        mod.robot_targets(tab)
    p = tmp_path / "t.json"
    p.write_text(json.dumps(_table()))
    assert mod.main([f"x={p}", "--out", str(tmp_path / "out")]) == 0
    md = (tmp_path / "out.md").read_text()
    assert "## x" in md and "| rough | 0.090 | 0.062 |" in md
    assert "| 3/3, -, 3/3 |" in md  # how many trained seeds and episodes each kind's value rests on
    with pytest.raises(SystemExit):
        mod.main([f"x={p}", "--out", str(tmp_path / "o2"), "--y-policy", "policy@old"])


def test_another_set_of_rows_read_as_the_headline(experiment, tmp_path):
    """``--ROBOT-headline``: the targets off other parts of the same table (a candidate setting
    merged beside the headline), checked against the table; the table's own headline untouched."""
    mod = experiment("closed_loop_targets")
    p = tmp_path / "t.json"
    p.write_text(json.dumps(_table()))
    assert mod.main([f"x={p}", "--out", str(tmp_path / "o"), "--x-headline", "pol,old:stride"]) == 0
    got = json.loads((tmp_path / "o.json").read_text())["robots"]["x"]
    rough = next(c for c in got["cells"] if c["scenario"] == "rough")
    assert rough["stride"]["falls"] == 1 and rough["onn"] is None  # old's STRIDE, no ONN part
    assert got["targets"]["no_falls"]["met"] is False
    assert "Headline parts: pol, old:stride" in (tmp_path / "o.md").read_text()
    assert json.loads(p.read_text())["headline"]["parts"] == ["pol", "a", "b"]
    for bad in (["--x-headline", "pol,nope"], ["--x-headline", "old:delan"], ["--y-headline", "pol"],
                ["--x-headline"], ["--x-headline", "--x-policy"]):
        with pytest.raises(SystemExit):
            mod.main([f"x={p}", "--out", str(tmp_path / "o2"), *bad])


def test_time_per_step_is_read_off_the_episodes_that_ran_alone(experiment):
    """A vmapped part's draws share each control step (four episodes' time in one row): the
    planner's time is the single episodes', and the draws' only where no single one ran."""
    mod = experiment("closed_loop_targets")
    tab = _table()
    for d in range(4):  # four vmapped draws of seed 0 on rough, 160 ms for the four together
        tab["rows"].append(dict(_row("rough", "stride@a", 0.061, "a", ms=160.0), seed=2 + d,
                                side_by_side=4))
    rough = next(c for c in mod.robot_targets(tab)["cells"] if c["scenario"] == "rough")
    assert rough["stride"]["ms_per_step"] == pytest.approx(80.0)
    assert rough["stride"]["episodes"] == 7
    tab["rows"] = [r for r in tab["rows"] if not (r["scenario"] == "rough" and r["model"].startswith("stride")
                                                   and "side_by_side" not in r)]
    rough = next(c for c in mod.robot_targets(tab)["cells"] if c["scenario"] == "rough")
    assert rough["stride"]["ms_per_step"] == pytest.approx(160.0)


def test_the_oracle_time_is_read_off_the_episodes_that_ran_alone(experiment):
    """An oracle row that shared its control steps with others (``--together``: five worlds in
    one program) took their time too: the ratio reads the oracle episodes that ran alone, from
    another scenario where this one has none alone; the shared ones only where none did."""
    mod = experiment("closed_loop_targets")
    tab = _table()
    tab["rows"] += [dict(_row(sc, "oracle", 0.05, "old", ms=2000.0), side_by_side=2,
                         scenarios_together="soft+rough") for sc in ("soft", "rough")]
    cells = {c["scenario"]: c for c in mod.robot_targets(tab)["cells"]}
    assert cells["rough"]["oracle_ms"] == pytest.approx(500.0)
    assert cells["soft"]["oracle_ms"] == pytest.approx(500.0)  # rough's alone, not 2000
    assert cells["soft"]["oracle_ms_from"] == "all scenarios"
    assert cells["soft"]["time_ratio"] == pytest.approx(80.0 / 500.0)
    tab["rows"] = [r for r in tab["rows"] if r.get("side_by_side") == 2 or r["model"] != "oracle"]
    cells = {c["scenario"]: c for c in mod.robot_targets(tab)["cells"]}
    assert cells["soft"]["oracle_ms"] == pytest.approx(2000.0)


def test_the_oracle_is_read_against_the_policy_as_a_reference(experiment):
    """The bar a right model sets (not a target): where the same planner through the scenario's
    own MJX model is above the policy, and where STRIDE is at most it; scenarios without an
    oracle row of the headline are left out of both."""
    mod = experiment("closed_loop_targets")
    tab = _table()
    r = mod.robot_targets(tab)
    assert r["oracle_reference"]["scenarios"] == []  # the oracle row of part "old" is not read
    assert "for reference" not in mod.markdown({"go1": r}, "cmd")
    tab["rows"] += [_row("rough", "oracle@pol", 0.05, "pol", ms=600.0),
                    _row("soft", "oracle@pol", 0.0512, "pol", ms=600.0)]
    r = mod.robot_targets(tab)
    ref = r["oracle_reference"]
    assert ref["scenarios"] == ["rough", "soft"] and ref["oracle_above_policy"] == ["soft"]
    # STRIDE: rough 0.062 above the oracle's 0.05; soft 0.052 above 0.0512 too
    assert ref["stride_at_most_oracle"] == [] and ref["stride_vs_oracle_of"] == 2
    md = mod.markdown({"go1": r}, "cmd")
    assert ("at most the policy in 1 of 2 scenarios (above it: soft 0.05120 against 0.05000); "
            "STRIDE at most the oracle in 0 of 2") in md
    # the baselines' target read for the oracle: ONN rough 0.072 / soft 0.047 against the
    # oracle's 0.05 / 0.0512 (no DeLaN rows: not compared)
    assert ref["oracle_vs_baselines_of"] == 2 and ref["oracle_above_baseline"] == ["soft (onn)"]
    assert "the oracle at most DeLaN + MLP's and ONN's in 1 of 2 comparisons (above: soft (onn))" in md
    tab["rows"][-1]["vel_rmse"] = 0.053  # the oracle above STRIDE on soft
    ref = mod.robot_targets(tab)["oracle_reference"]
    assert ref["stride_at_most_oracle"] == ["soft"]
    tab["rows"][-1]["fell"] = True  # an oracle that falls is above anything that stays up
    ref = mod.robot_targets(tab)["oracle_reference"]
    assert ref["oracle_above_policy"] == ["soft"] and ref["stride_at_most_oracle"] == ["soft"]


def test_a_timing_episode_without_tracking_is_no_tracking_cell(experiment):
    """An oracle row that stayed up with a NaN error (an episode run only to time the
    controller, shorter than the settling time) says nothing of tracking: no oracle cell, so
    no reference line, while its time still counts; an oracle that fell with a NaN error is a
    loss, as before."""
    mod = experiment("closed_loop_targets")
    tab = _table()
    tab["rows"].append(_row("rough", "oracle@pol", float("nan"), "pol", ms=600.0))
    r = mod.robot_targets(tab)
    rough = next(c for c in r["cells"] if c["scenario"] == "rough")
    assert rough["oracle"] is None and rough["stride_vs_oracle"] is None
    assert r["oracle_reference"]["scenarios"] == []
    assert rough["oracle_ms"] == pytest.approx(550.0)  # its time: with part "old"'s 500
    tab["rows"][-1]["fell"] = True
    rough = next(c for c in mod.robot_targets(tab)["cells"] if c["scenario"] == "rough")
    assert rough["oracle"]["falls"] == 1 and rough["stride_vs_oracle"] is True


def test_the_oracle_is_read_at_strides_samples_and_horizon(experiment):
    """The oracle's time and tracking come from rows at STRIDE's K and H (a planner's time
    follows its horizon: G1's oracle took half its H 20 time at H 10); a scenario where STRIDE
    ran at a size no oracle row has leaves the time target not measured, never judged against
    the oracle of another size. Rows that record no size (older tables) are read as before."""
    mod = experiment("closed_loop_targets")
    tab = _table()
    sized = lambda r, k, h: dict(r, K=k, H=h)
    tab["rows"] = [sized(r, 1024, 10) if r["model"].startswith("stride") else r for r in tab["rows"]]
    tab["rows"][-1] = sized(tab["rows"][-1], 1024, 20)  # the oracle at H 20 (500 ms)
    tab["rows"] += [_row("rough", "oracle@pol", 0.05, "pol", ms=600.0)]  # recorded no size
    tab["rows"][-1] = sized(tab["rows"][-1], 1024, 20)
    r = mod.robot_targets(tab)
    cells = {c["scenario"]: c for c in r["cells"]}
    assert cells["rough"]["oracle_ms"] is None and cells["rough"]["oracle"] is None
    assert cells["rough"]["time_ratio"] is None
    tf = r["targets"]["time_fifth_of_oracle"]
    assert tf["met"] is None and tf["no_oracle_at_stride_size"] == ["rough", "soft"]
    assert "no oracle row at STRIDE's K and H in rough (K 1024, H 10)" in mod.markdown({"g1": r}, "cmd")
    # an oracle at H 10 alone, on rough: its time (and, in the headline, its tracking) is read
    tab["rows"] += [sized(_row("rough", "oracle@pol", 0.055, "pol", ms=250.0), 1024, 10)]
    r = mod.robot_targets(tab)
    cells = {c["scenario"]: c for c in r["cells"]}
    assert cells["rough"]["oracle_ms"] == pytest.approx(250.0)
    assert cells["rough"]["oracle"]["vel_rmse"] == pytest.approx(0.055)
    assert cells["soft"]["oracle_ms_from"] == "all scenarios"  # rough's H 10 row
    assert r["targets"]["time_fifth_of_oracle"]["met"] is False  # 80 / 250 > 1/5
    # a table whose rows record no size: the oracle of any size, as before
    r = mod.robot_targets(_table())
    assert r["targets"]["time_fifth_of_oracle"]["met"] is True  # 80 / 500


def test_the_controllers_times_come_from_timing_parts(experiment, tmp_path):
    """``--ROBOT-timing PART,...``: where the headline's rows ran many episodes side by side
    and hold no controller's time, parts run to time the controllers give STRIDE's and the
    oracle's own times (of the same scenario, else all theirs), at the headline STRIDE's K and
    H only; a timing part the table lacks, or one without a timed row, is an error."""
    mod = experiment("closed_loop_targets")
    tab = _table()
    sized = lambda r, **kw: dict(r, K=1024, H=10, **kw)
    tab["rows"] = [sized(r) if r["model"].startswith("stride") or r["model"] == "oracle" else r
                   for r in tab["rows"]]
    tab["rows"] += [sized(_row("rough", "stride@tm", 0.06, "tm", ms=60.0), controller_ms=40.0),
                    sized(_row("rough", "oracle@tm", 0.05, "tm", ms=900.0), controller_ms=400.0),
                    dict(_row("soft", "oracle@tm", 0.05, "tm", ms=900.0), K=1024, H=20,
                         controller_ms=800.0)]  # another horizon: not read
    tab["parts"]["tm"] = {}
    before = {c["scenario"]: c for c in mod.robot_targets(tab)["cells"]}
    assert before["rough"]["time_basis"] == "closed-loop step"  # 80 / 500
    r = mod.robot_targets(tab, timing=("tm",))
    cells = {c["scenario"]: c for c in r["cells"]}
    for sc in ("rough", "soft"):  # soft: rough's timed rows, its own H 20 oracle left out
        assert cells[sc]["time_basis"] == "controller" and cells[sc]["controller_ms_from"] == "timing parts"
        assert cells[sc]["time_ratio"] == pytest.approx(40.0 / 400.0)
    assert cells["rough"]["stride"]["episodes"] == 3  # the timing row is not a headline episode
    md = mod.markdown({"g1": r}, "cmd")
    assert "40.0 c" in md and "from the timing parts tm" in md
    with pytest.raises(ValueError, match="'nope': no row"):
        mod.robot_targets(tab, timing=("nope",))
    with pytest.raises(ValueError, match="--controller-repeats"):
        mod.robot_targets(tab, timing=("pol",))
    p = tmp_path / "closed_loop.json"
    p.write_text(json.dumps(tab))
    assert mod.main([f"g1={p}", "--g1-timing", "tm", "--out", str(tmp_path / "t")]) == 0
    assert json.loads((tmp_path / "t.json").read_text())["robots"]["g1"]["targets"][
        "time_fifth_of_oracle"]["worst_ratio"] == pytest.approx(0.1)
    with pytest.raises(SystemExit):
        mod.main([f"g1={p}", "--go1-timing", "tm", "--out", str(tmp_path / "t")])


def test_the_time_ratio_reads_both_times_off_one_card(experiment):
    """An H100 runs the oracle slower than an H200: a ratio of STRIDE's time on one card to the
    oracle's on another would flatter (or wrong) STRIDE. Each ratio pairs the two on a card both
    ran on (the worst over such cards); where the oracle ran only on other cards than STRIDE the
    target is not measured there, and says so."""
    mod = experiment("closed_loop_targets")
    tab = _table()
    tab["parts"] = {p: {"device": "H200"} for p in tab["parts"]}
    tab["parts"]["slow"] = {"device": "H100"}
    tab["rows"].append(_row("rough", "oracle", 0.07, "slow", ms=2000.0))  # the H100's
    r = mod.robot_targets(tab)
    cells = {c["scenario"]: c for c in r["cells"]}
    assert cells["rough"]["oracle_ms"] == pytest.approx(500.0)  # the H200's alone, not 1250
    assert cells["rough"]["time_device"] == "H200"
    assert cells["rough"]["time_ratio"] == pytest.approx(80.0 / 500.0)
    assert "one card (H200)" in mod.markdown({"go1": r}, "cmd")
    # STRIDE's seed 2 on the H100 too: that card's pair (90 / 2000) is the better ratio; the
    # worst over the cards both ran on is read
    tab["rows"].append(_row("rough", "stride_s2@slow", 0.06, "slow", ms=90.0))
    rough = next(c for c in mod.robot_targets(tab)["cells"] if c["scenario"] == "rough")
    assert rough["time_device"] == "H200" and rough["time_ratio"] == pytest.approx(80.0 / 500.0)
    # the oracle on the H100 alone: not measured, named
    tab = _table()
    tab["parts"] = {p: {"device": "H100" if p == "old" else "H200"} for p in tab["parts"]}
    r = mod.robot_targets(tab)
    tf = r["targets"]["time_fifth_of_oracle"]
    assert tf["met"] is None and tf["no_oracle_at_stride_size"] == []
    assert tf["oracle_on_other_cards"] == {"rough": ["H100"], "soft": ["H100"]}
    assert "only on other cards than STRIDE in rough (H100), soft (H100)" in mod.markdown(
        {"go1": r}, "cmd")
    # timing parts on two cards: the controllers paired on the one both were timed on
    tab["parts"].update(tm={"device": "H100"}, tm2={"device": "H200"})
    tab["rows"] += [dict(_row("rough", "stride@tm", 0.06, "tm", ms=60.0), controller_ms=50.0),
                    dict(_row("rough", "oracle@tm", 0.05, "tm", ms=900.0), controller_ms=600.0),
                    dict(_row("rough", "stride@tm2", 0.06, "tm2", ms=60.0), controller_ms=40.0)]
    rough = next(c for c in mod.robot_targets(tab, timing=("tm", "tm2"))["cells"]
                 if c["scenario"] == "rough")
    assert rough["controller_ms_from"] == "timing parts" and rough["time_device"] == "H100"
    assert rough["time_ratio"] == pytest.approx(50.0 / 600.0)
