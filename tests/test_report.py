"""results/REPORT.md from synthetic result files: verdicts follow the numbers, absent inputs are
'not run', a missing Table I is a clear error."""

import json
import pathlib

import pytest

from stride_paper import report



def _run(model, seed, state, force=None, stance=60.0, growth=1.5):
    ph = [1.0] * 14 + [1.0] + [1.0] * 14 + [growth]  # e(15) = 1, e(30) = growth
    r = {"run": f"runs/x/{model}-s{seed}", "model": model, "seed": seed,
         "state": {"mean": state, "spread": 0.0, "per_horizon": ph, "windows": 8,
                   "diverged": 0.0 if state == state else 1.0}}
    if force is not None:
        r["force"] = {"mean": force, "mean_true_normal": stance}
    return r


def _table(robot, stride_state=5.0, stride_force=6.0):
    runs = []
    for s in (0, 1):
        runs += [_run("stride", s, stride_state + 0.1 * s, stride_force + 0.1 * s),
                 _run("delan", s, 10.0 + 0.1 * s, 10.0, growth=1.3),
                 _run("lnn_diffusion", s, float("nan") if s else 12.0, 30.0),
                 _run("onn", s, 11.0, growth=2.5),
                 _run("diffusion", s, 20.0)]
    return {"command": f"python experiments/table1.py --robot {robot} --preset paper",
            "table": {}, "runs": runs, "backend": "cpu"}


def _summary(tag="tiny", free=0.05, contact=0.8, w1_stride=0.5):
    one = lambda v: {"mean": v, "std": 0.0, "n": 1}
    phase_models = {"stride": {"w1_near": one(w1_stride), "w1_near_over_floor": one(w1_stride)},
                    "delan": {"w1_near": one(1.0), "w1_near_over_floor": one(1.0)},
                    "onn": {"w1_near": one(1.1), "w1_near_over_floor": one(1.1)}}
    return {"tag": tag, "device": "cpu", "commands": {p: f"python experiments/reproduce.py "
                                                         f"--preset {tag}" for p in
                                                      ("phase", "allocation", "nfe")},
            "phase": {"models": phase_models,
                      "per_seed": [{k: {"w1_near": v["w1_near"]["mean"]}
                                    for k, v in phase_models.items()}],
                      "figure": "phase_portrait.png"},
            "allocation": {"share": {"free": {"mean": free, "std": 0.01, "n": 2},
                                     "contact": {"mean": contact, "std": 0.02, "n": 2}},
                           "figure": "residual_allocation.png"},
            "nfe": {"curves": {
                "stride": {"nfe": [1, 2], "error_mean": [9.0, 8.0], "error_std": [1, 1],
                           "residual_batch_hz": [900.0, 500.0], "batch": 256},
                "lnn_diffusion": {"nfe": [1, 2, 10], "error_mean": [20.0, 15.0, 8.5],
                                  "error_std": [1, 1, 1],
                                  "residual_batch_hz": [800.0, 400.0, 90.0], "batch": 256}},
                "delan": {"error_mean": 8.5, "error_std": 0.5}},
            "claims": []}


def _bench(kind, ms):
    rows = [{"robot": "go1", "model": "stride", "K": 128 if kind == "cpu" else 1024,
             "H": 16 if kind == "cpu" else 30, "substeps": 1, "nfe": 2, "ms": ms,
             "hz": 1000 / ms, "ratio": 2.0}]
    return {"env": {"command": f"stride bench-mppi --preset {kind}", "device": kind,
                    "config": {"repeats": 5}}, "rows": rows}


def _closed(stride_rmse=0.2, fell=False):
    rows = [{"scenario": sc, "model": m, "vel_rmse": v, "fell": f}
            for sc in ("step", "slope") for m, v, f in
            (("stride", stride_rmse, fell), ("delan", 0.4, False), ("oracle", 0.1, False))]
    return {"env": {"command": "python -m stride_jax.control.closed_loop", "device": "cpu"},
            "rows": rows}


def _write(path: pathlib.Path, d):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(d))


@pytest.fixture
def results(tmp_path):
    r = tmp_path / "results"
    for robot in ("go1", "g1"):
        _write(r / "table1" / robot / "table.json", _table(robot))
    return r


def _full(r):
    _write(r / "reproduce" / "tiny" / "summary.json", _summary())
    (r / "reproduce" / "tiny" / "phase_portrait.png").write_bytes(b"png")
    _write(r / "mppi_latency" / "bench_mppi_cpu.json", _bench("cpu", 10.0))
    _write(r / "mppi_latency" / "bench_mppi_gpu.json", _bench("gpu", 2.0))
    _write(r / "closed_loop_test" / "closed_loop.json", _closed())
    _write(r / "gap_bench.json", {"command": "stride gap bench", "summary": {}})


def _verdicts(r):
    return {row.claim: row.verdict for row in report.build(r)["rows"]}


def _find(v: dict, *words):
    hits = [k for k in v if all(w in k for w in words)]
    assert len(hits) == 1, (words, hits)
    return v[hits[0]]


def test_verdicts_follow_numbers(results):
    _full(results)
    v = _verdicts(results)
    assert _find(v, "Go1", "state error >= 20% below DeLaN") == report.HOLDS  # 0.5
    assert _find(v, "G1", "foot-force error ~30%") == report.HOLDS  # 0.6
    assert _find(v, "Go1", "lowest 30-step state RMSE") == report.HOLDS
    assert _find(v, "Go1", "ONN's error grows faster") == report.HOLDS  # 2.5 vs 1.3
    assert _find(v, "Go1", "mean stance force") == report.HOLDS  # 6 / 60 <= 13%
    assert _find(v, "G1", "mean stance force") == report.FAILS  # 6 / 60 > 8%
    assert _find(v, "free swing small") == report.HOLDS
    assert _find(v, "closer to the truth than DeLaN") == report.HOLDS
    assert _find(v, "at every common NFE") == report.HOLDS
    assert _find(v, "smallest NFE within 5%") == report.HOLDS  # CFM 500/s at 2, DDPM 90/s at 10
    assert _find(v, "fewer NFEs") == report.HOLDS  # CFM at NFE 2, DDPM at 10
    assert _find(v, "2-core CPU") == report.HOLDS  # 10 ms = 100 Hz
    assert _find(v, "on a GPU") == report.HOLDS
    assert _find(v, "without falling") == report.HOLDS
    assert _find(v, "as good as DeLaN's and ONN's") == report.HOLDS

    # Flip the numbers: the verdicts flip.
    for robot in ("go1", "g1"):
        _write(results / "table1" / robot / "table.json",
               _table(robot, stride_state=9.0, stride_force=9.5))
    _write(results / "reproduce" / "tiny" / "summary.json",
           _summary(free=0.5, w1_stride=1.5))
    _write(results / "mppi_latency" / "bench_mppi_cpu.json", _bench("cpu", 30.0))
    _write(results / "mppi_latency" / "bench_mppi_gpu.json", _bench("gpu", 12.0))
    _write(results / "closed_loop_test" / "closed_loop.json", _closed(0.05, fell=True))
    v = _verdicts(results)
    assert _find(v, "Go1", "state error >= 20% below DeLaN") == report.FAILS  # 0.9
    assert _find(v, "G1", "foot-force error ~30%") == report.FAILS  # 0.95
    assert _find(v, "Go1", "lowest 30-step state RMSE") == report.HOLDS  # 9 < 10 still
    assert _find(v, "free swing small") == report.FAILS
    assert _find(v, "closer to the truth than DeLaN") == report.FAILS
    assert _find(v, "2-core CPU") == report.FAILS
    assert _find(v, "on a GPU") == report.FAILS
    assert _find(v, "without falling") == report.FAILS
    # STRIDE's error while upright is lower, but it falls where DeLaN does not: worse.
    assert _find(v, "as good as DeLaN's and ONN's") == report.FAILS


def test_report_text(results):
    _full(results)
    md = report.write(results)["markdown"]
    assert (results / "REPORT.md").read_text() == md
    assert "WARNING" in md and "`tiny` preset" in md
    assert "[phase_portrait.png](reproduce/tiny/phase_portrait.png)" in md
    assert "python experiments/table1.py --robot go1 --preset paper" in md
    assert "stride bench-mppi --preset cpu" in md
    assert "## How to regenerate" in md
    # LNN + Diffusion's seed 1 has no finite state error: said, not averaged.
    assert "LNN + Diffusion diverged on seed(s) 1" in md
    # The paper preset is preferred over tiny when present.
    _write(results / "reproduce" / "paper" / "summary.json", _summary(tag="paper"))
    md = report.build(results)["markdown"]
    assert "preset `paper`" in md and "WARNING" not in md


def test_missing_optional_inputs_are_not_run(results):
    rep = report.build(results)
    rows = rep["rows"]
    by = {r.claim: r for r in rows}
    for words in (("free swing small",), ("at every common NFE",), ("2-core CPU",), ("on a GPU",),
                  ("without falling",), ("closer to the truth than DeLaN",)):
        assert _find({k: r.verdict for k, r in by.items()}, *words) == report.NOT_RUN
    assert _find({k: r.verdict for k, r in by.items()}, "Go1", "20% below") == report.HOLDS
    md = rep["markdown"]
    assert "not yet run" in md and "no `results/gap_bench.json`" in md
    # Closed-loop files without STRIDE rows: still "not yet run".
    c = _closed()
    c["rows"] = [r for r in c["rows"] if r["model"] != "stride"]
    _write(results / "closed_loop" / "closed_loop_cpu" / "closed_loop.json", c)
    assert _find(_verdicts(results), "without falling") == report.NOT_RUN


def test_closed_loop_claims_read_the_headline_parts_alone(results):
    """A merged table naming its ``headline`` parts (the current planner): the closed-loop claims
    read those parts' rows alone, every trained seed and draw under its kind (``stride_s1``,
    ``stride@part``), and no file without a headline; without one, every file's rows count."""
    _full(results)
    _write(results / "closed_loop_test" / "closed_loop.json", _closed(0.05, fell=True))  # old
    row = lambda sc, m, v, part, fell=False: dict(scenario=sc, model=m, vel_rmse=v, fell=fell,
                                                  part=part)
    merged = {"parts": {"old": {"command": "a"}, "new": {"command": "b"}},
              "headline": {"parts": ["new"]},
              "rows": [row("tilt", "stride", 0.9, "old", fell=True), row("tilt", "onn", 0.5, "old"),
                       row("tilt", "stride@new", 0.85, "new"), row("tilt", "stride_s1@new", 0.87, "new"),
                       row("tilt", "onn@new", 0.8, "new", fell=True), row("tilt", "onn_s1@new", 0.7, "new"),
                       row("soft", "stride@new", 0.15, "new"), row("soft", "delan@new", 0.2, "new")]}
    _write(results / "closed_loop_g1_gpu" / "closed_loop.json", merged)
    rows = {r.claim: r for r in report.build(results)["rows"]}
    fall = _find({k: r for k, r in rows.items()}, "without falling")
    assert fall.verdict == report.HOLDS and "fell in 0 of 3 runs over 2 scenarios" in fall.ours
    assert "the current planner: new of closed_loop_g1_gpu" in fall.ours
    assert fall.command == "b"  # the headline part's command, not the history's
    # the tilt runs kept no sense_gravity: their controller read world down, and the claim says so
    assert "2 of these runs are on slopes their controller could not sense" in fall.ours
    merged["parts"]["new"]["config"] = {"sense_gravity": True}
    _write(results / "closed_loop_g1_gpu" / "closed_loop.json", merged)
    fall = _find({r.claim: r for r in report.build(results)["rows"]}, "without falling")
    assert "could not sense" not in fall.ours and "fell in 0 of 3 runs" in fall.ours
    best = _find({k: r for k, r in rows.items()}, "as good as DeLaN's and ONN's")
    # tilt: STRIDE 0 of 2 fell, ONN 1 of 2; soft: 0.15 against DeLaN's 0.2
    assert best.verdict == report.HOLDS and "at most in 2 of 2 comparisons" in best.ours
    merged["rows"].append(row("soft", "onn_s2@new", 0.1, "new"))
    _write(results / "closed_loop_g1_gpu" / "closed_loop.json", merged)
    best = _find({r.claim: r for r in report.build(results)["rows"]}, "as good as DeLaN's")
    assert best.verdict == report.FAILS and "soft vs ONN" in best.ours
    # a loss over several trained seeds says whether the seeds tell the kinds apart
    seeds = lambda m, vs: [row("push", f"{m}_s{i}@new" if i else f"{m}@new", v, "new")
                           for i, v in enumerate(vs)]
    for onn, apart in (([0.101, 0.103, 0.102], "told apart"),
                       ([0.08, 0.125, 0.10], "not told apart")):
        merged["rows"] = [r for r in merged["rows"] if r["scenario"] != "push"] + \
            seeds("stride", [0.110, 0.112, 0.111]) + seeds("onn", onn)
        _write(results / "closed_loop_g1_gpu" / "closed_loop.json", merged)
        best = _find({r.claim: r for r in report.build(results)["rows"]}, "as good as DeLaN's")
        assert f"over 3 / 3 trained seeds: {apart}" in best.ours, best.ours
        if apart == "told apart":
            assert "push vs ONN (plain MLP) by 0.0090 m/s" in best.ours
    # a merged table with more models than scenarios: a row per model, a column per scenario
    md = report.build(results)["markdown"]
    assert "| model | tilt | soft | push |" in md and "| stride_s1@new | 0.870 | - | 0.112 |" in md
    # lost on falls (its upright error lower): said in falls, not as a velocity margin
    merged["rows"] = [r for r in merged["rows"] if r["scenario"] != "push"] + \
        seeds("stride", [0.05, 0.05, 0.05]) + seeds("onn", [0.1, 0.1, 0.1])
    merged["rows"][-4]["fell"] = True
    _write(results / "closed_loop_g1_gpu" / "closed_loop.json", merged)
    best = _find({r.claim: r for r in report.build(results)["rows"]}, "as good as DeLaN's")
    assert "push vs ONN (plain MLP): fell 1 of 3 against 0 of 3" in best.ours, best.ours
    assert "1 worse on falls" in best.ours
    # a headline of several parts, each model run in its own (one planner, split over device
    # calls): compared across them
    merged["parts"]["new_b"] = {"command": "c"}
    merged["headline"]["parts"].append("new_b")
    merged["rows"] = [r for r in merged["rows"] if r["scenario"] != "push"] + \
        [row("lowf", "stride@new", 0.05, "new"), row("lowf", "delan@new_b", 0.04, "new_b")]
    _write(results / "closed_loop_g1_gpu" / "closed_loop.json", merged)
    best = _find({r.claim: r for r in report.build(results)["rows"]}, "as good as DeLaN's")
    assert "lowf vs DeLaN" in best.ours, best.ours
    assert best.command == "b ; c"
    # a history of many parts: the table's line says where their commands are instead
    merged["parts"].update({f"old_{i}": {"command": f"x{i}"} for i in range(4)})
    _write(results / "closed_loop_g1_gpu" / "closed_loop.json", merged)
    built = report.build(results)
    assert "merged from 7 parts (`experiments/closed_loop_merge.py`), each part's command kept" in built["markdown"]
    assert " ; x0" not in built["markdown"]
    assert _find({r.claim: r for r in built["rows"]}, "as good as DeLaN's").command == "b ; c"
    del merged["headline"]  # no headline anywhere: the history, every file, names as they are
    _write(results / "closed_loop_g1_gpu" / "closed_loop.json", merged)
    assert _find(_verdicts(results), "without falling") == report.FAILS


def test_all_seeds_diverged_is_not_measurable(results):
    t = _table("go1")
    for r in t["runs"]:
        if r["model"] == "delan":
            r["state"]["mean"] = float("nan")
    _write(results / "table1" / "go1" / "table.json", t)
    v = _verdicts(results)
    assert _find(v, "Go1", "state error >= 20% below DeLaN") == report.NOT_MEASURABLE


def test_missing_table1_names_the_file(results):
    (results / "table1" / "g1" / "table.json").unlink()
    with pytest.raises(FileNotFoundError, match=r"g1/table\.json"):
        report.build(results)


def test_paper_constants_match_claims():
    from stride_paper import claims
    assert report.PAPER_TABLE1 == claims.PAPER_TABLE


def test_script(results, tmp_path, experiment):
    mod = experiment("report")
    out = tmp_path / "R.md"
    rep = mod.main(["--results", str(results), "--out", str(out)])
    assert out.read_text() == rep["markdown"]
    assert rep["path"] == out


def test_further_data_sets_get_their_own_ratios_and_targets(results):
    runs = []
    for s in (0, 1):
        runs += [_run("stride", s, 7.0, 7.0), _run("delan", s, 10.0, 10.0),
                 _run("stride[acc_through=mean]", s, 9.5, 9.0)]
        runs[-3]["distribution"] = {"energy": 0.3, "crps": 0.2}
        runs[-2]["distribution"] = {"energy": 0.5, "crps": 0.25}
    _write(results / "table1" / "go1_walk" / "table.json",
           {"command": "python experiments/table1.py --data walk", "runs": runs})
    md = report.build(results)["markdown"]
    assert "## STRIDE against DeLaN, per data set" in md
    section = md[md.index("### `go1_walk`"):]
    rows = [line for line in section.splitlines() if line.startswith("| stride")]
    state = [r for r in rows if r.startswith("| stride | state")][0]
    assert "0.70" in state and "| holds |" in state  # 0.70 <= 0.80
    force = [r for r in rows if r.startswith("| stride | force")][0]
    assert "0.70" in force and "| holds |" in force  # 0.70 <= 0.75
    mean_state = [r for r in rows if r.startswith("| stride[acc_through=mean] | state")]
    assert "0.95" in mean_state[0] and "does not hold" in mean_state[0]
    energy = [r for r in rows if r.startswith("| stride | energy score")][0]
    assert "0.60" in energy and "(better)" in energy


def test_gap_controls_are_reported_from_their_own_file(results):
    from stride_paper import report_control

    rel = lambda p: p.relative_to(results).as_posix()
    _write(results / "gap_bench.json", {"command": "stride gap bench", "summary": {}})
    assert not any("No-effect controls" in x for x in report_control.gap_lines(results, rel))
    _write(results / "gap_bench_go1_independent_controls.json",
           {"command": "stride gap bench-independent --preset controls",
            "summary": {"noise_free": {"controls_detected": 4, "controls_named": 1, "controls": 20,
                                       "confident_false": 0}}})
    text = "\n".join(report_control.gap_lines(results, rel))
    assert "No-effect controls" in text and "--preset controls" in text
    assert "noise_free: a gap called on top of the calibrated settings in 4 of 20, a physical effect named in 1, " \
           "confidently in 0" in text


def test_a_result_copied_from_another_and_changed_is_dated_by_its_own_commit(tmp_path):
    # git log --follow sees a new result file much like an older one as a copy of it (status C);
    # the note must give the commit that added this content, not the older file's
    import subprocess
    from stride_paper.report_common import _git_note
    git = lambda *a: subprocess.run(["git", *a], cwd=tmp_path, check=True, capture_output=True, text=True)
    git("init", "-q")
    git("config", "user.email", "t@t"); git("config", "user.name", "t")
    rows = "\n".join(f'"row {i}": {i}' for i in range(40))
    (tmp_path / "a").mkdir(); (tmp_path / "b").mkdir()
    (tmp_path / "a" / "r.json").write_text(rows + '\n"ms": 8.78\n')
    git("add", "."); git("commit", "-q", "-m", "first")
    first = git("log", "-1", "--format=%h").stdout.strip()
    (tmp_path / "b" / "r.json").write_text(rows + '\n"ms": 5.04\n')
    git("add", "."); git("commit", "-q", "-m", "second")
    second = git("log", "-1", "--format=%h").stdout.strip()
    assert _git_note(tmp_path / "a" / "r.json").startswith(f"committed {first}")
    assert _git_note(tmp_path / "b" / "r.json").startswith(f"committed {second}")


def test_tables_with_other_rows_beside_closed_loop_runs_are_not_read_as_runs(tmp_path):
    """A probe's table kept in a closed-loop folder (rows of noise levels, no tracking error)
    is not a closed-loop run: the report reads the run beside it alone."""
    from stride_paper import report_control
    run = _closed()
    _write(tmp_path / "closed_loop" / "a" / "closed_loop.json", run)
    _write(tmp_path / "closed_loop" / "a" / "margins.json",
           {"command": "policy_noise.py", "rows": [{"noise": 0.0, "draws": 16, "falls": 0}]})
    found = report_control.load_closed_loop(tmp_path)
    assert [p.name for p, _ in found] == ["closed_loop.json"]
