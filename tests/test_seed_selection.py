"""experiments/seed_selection.py: the seed a training's validation loss picks, beside the seed
that plans best, read off a merged table's headline."""

import json

import pytest


def _models(tmp_path, losses):
    for (kind, seed), val in losses.items():
        d = tmp_path / "models" / f"{kind}-s{seed}"
        d.mkdir(parents=True)
        (d / "summary.json").write_text(json.dumps({"best_val": val}))
    return tmp_path / "models"


def _table():
    rows = []
    # stride: seed 1 plans best on rough, seed 2 on soft; onn: seed 0 best everywhere;
    # a fallen draw of stride seed 1 on soft is not counted in its mean
    errs = {("stride", "rough"): [0.07, 0.05, 0.06], ("stride", "soft"): [0.05, 0.06, 0.04],
            ("onn", "rough"): [0.05, 0.06, 0.07], ("onn", "soft"): [0.04, 0.05, 0.06]}
    for (kind, sc), vs in errs.items():
        for s, v in enumerate(vs):
            name = kind + (f"_s{s}" if s else "")
            rows.append(dict(scenario=sc, model=f"{name}@a", vel_rmse=v, fell=False,
                             run=f"fm/slope/{kind}-s{s}", part="a"))
    rows.append(dict(scenario="soft", model="stride_s1@a", vel_rmse=0.5, fell=True,
                     run="fm/slope/stride-s1", part="a"))
    rows.append(dict(scenario="soft", model="stride@old", vel_rmse=0.01, fell=False,
                     run="fm/other/stride-s0", part="old"))  # outside the headline: not read
    return {"parts": {"a": {}, "old": {}}, "headline": {"parts": ["a"]}, "rows": rows}


def test_the_pick_is_the_lowest_validation_loss_and_hits_are_counted(experiment, tmp_path):
    mod = experiment("seed_selection")
    models = _models(tmp_path, {("stride", 0): 3.0, ("stride", 1): 2.9, ("stride", 2): 3.1,
                                ("onn", 0): 2.0, ("onn", 1): 2.5, ("onn", 2): 2.2})
    r = mod.robot_selection(_table(), models)
    cells = {(c["scenario"], c["kind"]): c for c in r["cells"]}
    assert cells[("rough", "stride")]["pick"] == 1 and cells[("rough", "stride")]["best"] == 1
    soft = cells[("soft", "stride")]
    assert soft["pick"] == 1 and soft["best"] == 2 and soft["picked"] == pytest.approx(0.06)
    assert soft["mean"] == pytest.approx(0.05)  # the fallen draw of seed 1 left out
    assert r["hits"]["stride"] == {"best_picked": 1, "of": 2}
    assert r["hits"]["onn"] == {"best_picked": 2, "of": 2}
    assert r["hits"]["delan"] == {"best_picked": 0, "of": 0}
    md = mod.markdown({"go1": r}, "cmd")
    assert "stride 1 of 2" in md and "stride: s1 in 2" in md


def test_a_run_without_its_summary_is_a_clear_error(experiment, tmp_path):
    mod = experiment("seed_selection")
    models = _models(tmp_path, {("stride", 0): 3.0, ("stride", 1): 2.9, ("stride", 2): 3.1,
                                ("onn", 0): 2.0, ("onn", 1): 2.5})
    with pytest.raises(FileNotFoundError, match="onn-s2"):
        mod.robot_selection(_table(), models)
    tab = _table()
    # STRIDE's seed 0 from two trainings (a row of another run folder named as seed 0)
    tab["rows"][1].update(run="fm/other/stride_b-s0", model="stride@a")
    with pytest.raises(ValueError, match="stride seed 0"):
        mod.robot_selection(tab, models)
    tab = _table()
    del tab["headline"]
    with pytest.raises(ValueError, match="headline"):
        mod.robot_selection(tab, models)
