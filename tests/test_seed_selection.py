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


def test_model_error_metrics_are_ranked_against_the_seeds_planning(experiment, tmp_path):
    mod = experiment("seed_selection")
    models = _models(tmp_path, {("stride", 0): 3.0, ("stride", 1): 2.9, ("stride", 2): 3.1,
                                ("onn", 0): 2.0, ("onn", 1): 2.5, ("onn", 2): 2.2})
    sel = mod.robot_selection(_table(), models)

    def row(name, seed, err, told=False, prior=False):
        phase = dict(steps=10, bias_norm=err, spread_norm=2 * err, joint_vel_rmse=-err)
        return {"model": name + (" (told gravity)" if told else ""), "run": f"x/{name.split('_')[0]}-s{seed}",
                "told_gravity": told, "prior_alone": prior, "before 1 s": dict(phase, bias_norm=9.0),
                "from 1 s": phase}

    # rough: STRIDE's seeds plan 0.07 / 0.05 / 0.06; its told-gravity rows order them so, the
    # plain rows (not read when told rows exist) and the prior-alone rows the other way
    rows = [row(n, s, e, told=True) for n, s, e in (("stride", 0, 3.0), ("stride_s1", 1, 1.0),
                                                     ("stride_s2", 2, 2.0))]
    rows += [row(n, s, e) for n, s, e in (("stride", 0, 1.0), ("stride_s1", 1, 3.0), ("stride_s2", 2, 2.0))]
    rows += [row("stride", 0, 0.1, told=True, prior=True)]
    errors = mod.model_errors({"rows": rows})
    assert errors[("stride", 1)]["bias_norm"] == 1.0 and errors[("stride", 0)]["phase"] == "from 1 s"
    out = mod.against_model_error(dict(cells=[c for c in sel["cells"] if c["kind"] == "stride"]),
                                  "rough", errors)
    (r,) = out
    assert r["bias_norm"]["spearman"] == pytest.approx(1.0) and r["bias_norm"]["lowest_is_best"]
    assert r["joint_vel_rmse"]["spearman"] == pytest.approx(-1.0)
    assert not r["joint_vel_rmse"]["lowest_is_best"]
    md = mod.markdown({"go1": dict(sel, model_error=out)}, "cmd")
    assert "rho +1.0, lowest plans best" in md
    with pytest.raises(ValueError, match="onn seed"):  # a kind the report does not hold
        mod.against_model_error(sel, "rough", errors)
    with pytest.raises(ValueError, match="no scenario 'tilt'"):  # named otherwise in the table
        mod.against_model_error(sel, "tilt", errors)


def test_seeds_picked_once_on_other_episodes_are_scored_against_the_targets(experiment):
    mod = experiment("seed_selection")
    tab = _table()
    for sc, v in (("rough", 0.055), ("soft", 0.045)):  # the policy's own rows
        tab["rows"].append(dict(scenario=sc, model="policy@a", vel_rmse=v, fell=False, part="a"))

    def row(name, seed, err):
        return {"model": name, "run": f"x/{name.split('_')[0]}-s{seed}", "told_gravity": False,
                "prior_alone": False, "from 0 s": dict(steps=10, bias_norm=err, spread_norm=-err,
                                                       joint_vel_rmse=1.0 + seed)}
    # bias picks stride seed 1 (0.05 on rough, 0.06 on soft) and onn seed 0; spread picks stride
    # seed 0 and onn seed 2; joints picks seed 0 of both
    errors = mod.model_errors({"rows": [row("stride", 0, 2.0), row("stride_s1", 1, 1.0), row("stride_s2", 2, 1.5),
                                        row("onn", 0, 1.0), row("onn_s1", 1, 2.0), row("onn_s2", 2, 3.0)]})
    p = mod.picked_once(tab, errors, "walk.json")
    bias, spread = p["rules"]["bias_norm"], p["rules"]["spread_norm"]
    assert bias["pick"] == {"stride": 1, "onn": 0} and spread["pick"] == {"stride": 0, "onn": 2}
    # bias: stride s1 0.05 <= policy 0.055 on rough, 0.06 > 0.045 on soft; against onn s0 (0.05, 0.04)
    # it ties on rough (at most) and loses on soft
    assert (bias["at_most_policy"], bias["of_policy"], bias["at_most_policy_met"]) == (1, 2, False)
    assert (bias["at_most_baselines"], bias["of_baselines"]) == (1, 2)
    assert [c["vel_rmse"] for c in bias["stride"]] == pytest.approx([0.05, 0.06])
    # spread: stride s0 0.07 / 0.05 against onn s2 0.07 / 0.06: at most on both, the policy on neither
    assert (spread["at_most_policy"], spread["at_most_baselines"], spread["at_most_baselines_met"]) == (0, 2, True)
    # the mean over seeds: stride 0.06 / 0.05 with seed 1's fall on soft (fewer falls first), onn
    # 0.06 / 0.05 with none: at most onn on rough only
    assert (p["mean"]["at_most_policy"], p["mean"]["at_most_baselines"]) == (0, 1)
    # hindsight: stride's best seed per scenario 0.05 / 0.04 against onn's 0.05 / 0.04
    assert (p["best_in_hindsight"]["at_most_policy"], p["best_in_hindsight"]["at_most_baselines"]) == (2, 2)
    assert p["best_in_hindsight"]["at_most_policy_met"]
    md = "\n".join(mod._picked_markdown(p))
    assert "| lowest bias_norm | s1, s0 | 1 of 2 | 1 of 2 | rough 0.0500, soft 0.0600 |" in md
    with pytest.raises(ValueError, match="no onn seed"):
        mod.picked_once(tab, {k: v for k, v in errors.items() if k != ("onn", 2)}, "walk.json")
