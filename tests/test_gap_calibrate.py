"""The nominal model as shipped, simulator settings as model-form hypotheses, and their calibration
(synthetic logs whose simulator settings are known)."""

import dataclasses
import json

import numpy as np
import pytest

from stride_jax.gap import baseline, calibrate, diagnose, fit, nominal, real
from stride_jax.jobs import gap_report as report
from stride_jax.gap.nominal import Settings

QUIET = lambda s: None


def _split_data(sm, trajs, k):
    tr, te = diagnose.split(len(trajs), 0.34, 0)
    train = fit.make_data([trajs[i] for i in tr], k)
    test = fit.make_data([trajs[i] for i in te], k)
    return train, test, diagnose.scale_of(sm, fit.make_data([trajs[i] for i in tr]))


def test_go1_nominal_is_the_shipped_mjcf_and_the_training_edit_is_a_settings_point():
    shipped, training = nominal.load("go1"), nominal.load("go1", "training")
    a, b = nominal.describe(shipped), nominal.describe(training)
    assert (a["cone"], a["timestep"], a["contacts"], a["foot_condim"]) == ("elliptic", 0.002, "model", 6)
    assert (b["cone"], b["timestep"], b["contacts"], b["foot_condim"]) == ("pyramidal", 0.004, "feet_only", 3)
    assert a["colliding_geoms"] > b["colliding_geoms"] == 5
    # the MJX-training form as settings on the shipped model replays exactly as the training model
    s = nominal.training_settings(shipped, training)
    _, logged = real.generate(training, {}, 2, 30, seed=0)
    data = fit.make_data(logged)
    scale = diagnose.scale_of(training, data)
    as_settings = nominal.apply(shipped, s)
    assert as_settings.n_substeps == training.n_substeps == 5
    assert baseline.gap_of(as_settings, logged, scale) < 1e-20
    assert baseline.gap_of(shipped, logged, scale) > 1.0  # the model-form difference is large
    # neutral settings reproduce the model bit for bit
    assert baseline.gap_of(nominal.apply(shipped, Settings()), logged, scale) == baseline.gap_of(shipped, logged, scale)


def test_bad_settings_and_config_are_clear_errors():
    with pytest.raises(ValueError, match="cone 'round'"):
        Settings(cone="round")
    with pytest.raises(ValueError, match="does not divide the control period"):
        nominal.apply(nominal.load("pendulum"), Settings(timestep=0.003))
    with pytest.raises(ValueError, match="unknown setting"):
        calibrate.CalibrateConfig(continuous="solref,friction")
    with pytest.raises(ValueError, match="calibrate.mode"):
        calibrate.CalibrateConfig(mode="maybe")
    with pytest.raises(ValueError, match="nominal model form"):
        nominal.load("go1", "mjx")


def test_timestep_and_integrator_calibrated_back_to_the_truth():
    sm = nominal.load("pendulum")
    truth = Settings(timestep=0.005, integrator="rk4")
    _, logged = real.generate(nominal.apply(sm, truth), {}, 6, 120, seed=3)
    train, test, scale = _split_data(sm, logged, 3)
    cal = calibrate.calibrate(sm, train, test, scale, calibrate.CalibrateConfig(), QUIET)
    rec = cal.record
    assert rec["applied"], rec
    ok_dt = cal.settings.timestep == 0.005 or 0.005 in rec["discrete_ties"].get("timestep", [])
    assert ok_dt and cal.settings.integrator == "rk4", rec
    assert rec["heldout_gap_calibrated"] < 1e-3 * rec["heldout_gap_nominal"]
    assert any("rk4" in line for line in rec["changed"])


def test_solref_calibrated_back_near_the_truth():
    sm = nominal.load("pendulum_bouncing")
    truth = Settings(solref_timeconst=2.0)
    _, logged = real.generate(nominal.apply(sm, truth), {}, 6, 150, seed=1)
    train, test, scale = _split_data(sm, logged, 3)
    cfg = calibrate.CalibrateConfig(discrete="", continuous="solref_timeconst,solref_dampratio", max_nfev=8)
    cal = calibrate.calibrate(sm, train, test, scale, cfg, QUIET)
    assert cal.record["applied"], cal.record
    assert abs(cal.settings.solref_timeconst - 2.0) < 0.2, cal.settings
    assert cal.record["shrink"] > 0.9


def test_matching_settings_stay_nominal_in_noisy_logs():
    sm = nominal.load("pendulum")
    _, logged = real.generate(sm, {}, 6, 120, seed=4, noise=real.SensorNoise())
    train, test, scale = _split_data(sm, logged, 3)
    cal = calibrate.calibrate(sm, train, test, scale, calibrate.CalibrateConfig(), QUIET)
    assert not cal.record["applied"] and cal.model is sm and cal.record["changed"] == []
    assert "match the nominal model" in baseline.sentence(cal.record)


def test_effect_on_top_of_a_model_form_difference_is_named_and_both_shrinks_reported(tmp_path):
    sm = nominal.load("pendulum")
    truth = Settings(timestep=0.005, integrator="rk4")
    _, logged = real.generate(nominal.apply(sm, truth), {"damping": 0.3}, 5, 120, seed=1)
    cfg = dataclasses.replace(diagnose.PRESETS["tiny"], pairs_of=0)
    out = diagnose.diagnose(sm, logged, cfg, log=QUIET)
    v, cal, hf = out["verdict"], out["calibration"], out["how_far"]
    assert v["verdict"] == "explained" and v["effects"] == ["damping"], v["reason"]
    assert abs(out["which"]["ranking"][0]["params"]["damping"][0] - 0.3) < 0.03
    assert cal["applied"] and cal["settings"]["integrator"] == "rk4", cal
    assert v["reason"].startswith("the simulator's settings are off: ") and "on top of that, explained" in v["reason"]
    assert v["model_form"] == cal["changed"]
    # the shrink against the nominal model and against the calibrated baseline
    assert hf["gap_final"] < hf["gap_baseline"] < hf["gap_nominal"]
    assert hf["shrink_vs_nominal"] > hf["shrink_vs_baseline"] > 0.9
    assert hf["calibration_shrink"] == pytest.approx(1 - hf["gap_baseline"] / hf["gap_nominal"])
    path = report.write(out, tmp_path / "rep")
    md = path.read_text()
    assert "## Model form: the simulator's settings (calibrated first)" in md
    assert "against the nominal model" in md and "against the calibrated baseline" in md
    assert "conditional on the simulator's settings above" in md  # what the intervals hold, said where they are
    d = json.loads((tmp_path / "rep" / "diagnosis.json").read_text())
    assert d["calibration"]["changed"] == cal["changed"] and "shrink_vs_baseline" in d["how_far"]
    # a contact effect screened for the second start that did not reach the share: nothing ran, so
    # nothing is reported of it (the report once read its held-out gap regardless)
    below = {"held_fixed": {"ground_friction": [0.9]}, "share": 0.03, "adopted": False}
    refined = dict(cal.get("refined") or {}, contact_effect_start=below)
    lines = report.calibration_section(dict(out, calibration=dict(cal, refined=refined)))
    assert lines and not any("Calibrated again from the start" in line for line in lines)
    # a joint group held by the refinement, and one the margin rule passed over, are said
    scr = {"loss_without": 9.0, "screen": [{"effect": "damping@calf", "value": 0.7, "loss": 1.0},
                                           {"effect": "damping", "value": 0.3, "loss": 4.0}]}
    grp = dict(cal.get("refined") or {}, held_fixed={"damping@calf": [0.7]}, folded={}, screen=scr,
               settings_moved=False)
    lines = report.calibration_section(dict(out, calibration=dict(cal, refined=grp)))
    assert "damping@calf is a joint group: its training loss was 25.0% of the best library effect's (damping)." in lines
    passed = dict(grp, held_fixed={"damping": [0.3]}, screen=dict(scr, group_not_held={
        "group": "damping@calf", "loss": 3.8, "library": "damping", "library_loss": 4.0, "margin": 0.1}))
    lines = report.calibration_section(dict(out, calibration=dict(cal, refined=passed)))
    assert any(line.startswith("The joint group damping@calf came within 10% of damping's") for line in lines)
    # an adopted recheck is reported in the section and in the verdict's clause
    chk = {"best": {"damping": [0.3]}, "refinement_held": {"armature": [0.05]}, "ran": True, "adopted": True,
           "heldout_gap": 0.01, "heldout_gap_before": 0.04, "p_value": 0.001}
    rechecked = dict(cal, recheck=chk, effects_held_fixed={"damping": [0.3]})
    lines = report.calibration_section(dict(out, calibration=rechecked))
    assert any("Checked again with the best hypothesis (damping)" in line and "adopted" in line for line in lines)
    assert "fitted again with the best hypothesis, damping, held fixed" in baseline.sentence(rechecked)
    assert "25.0% of the held-out gap" in baseline.sentence(rechecked)
    # calibration off: the nominal model is the baseline, the effect is still named
    off = diagnose.diagnose(sm, logged, dataclasses.replace(cfg, calibrate=calibrate.CalibrateConfig(mode="off")),
                            log=QUIET)
    assert off["calibration"] == {"mode": "off", "applied": False}
    assert off["how_far"]["gap_baseline"] == off["how_far"]["gap_nominal"]
    assert np.isfinite(off["how_far"]["shrink_vs_nominal"])


def test_settings_kept_for_the_effect_held_on_top_say_so():
    # the refinement keeps settings that lower the held-out gap with the screened effect on top;
    # alone they may widen it (measured: kp_scale 0.7 on the Go1, -30%), and the clause says why
    rec = {"mode": "fit", "applied": True, "changed": ["time step: 2 ms -> 1 ms"], "shrink": -0.3, "k": 3,
           "p_value": 1.0, "effects_held_fixed": {"kp_scale": [0.75]}}
    s = baseline.sentence(rec)
    assert "fitted with kp_scale held fixed on top, with which they lower the held-out gap; without it they " \
           "close -30.0%" in s
    assert "held fixed" not in baseline.sentence(rec | {"shrink": 0.2})


def test_parsimony_puts_back_only_the_settings_that_do_not_matter():
    # a loss that cares about the time constant (x 1.6) and barely about the margin (6.5 microns)
    loss = lambda s: 1.0 + 50 * (s.solref_timeconst - 1.6) ** 2 + 1e3 * s.margin
    s = Settings(solref_timeconst=1.6, solimp_softness=1.0, margin=6.5e-6)
    out, L = calibrate.parsimony(s, loss(s), ["solref_timeconst", "solimp_softness", "margin"], loss, 0.01)
    assert out.margin == 0.0 and out.solref_timeconst == 1.6 and L == loss(out)
    # a margin that matters stays
    loss2 = lambda s: 1.0 + 1e4 * abs(s.margin - 0.002)
    s2 = Settings(margin=0.002)
    assert calibrate.parsimony(s2, loss2(s2), ["margin"], loss2, 0.01)[0].margin == 0.002


def test_solimp_softness_moves_d0_and_dmax_even_from_a_dmax_of_one():
    """Menagerie's Go1 feet have solimp dmax = 1: a factor on ``1 - d`` alone could never move it;
    from MuJoCo's floor (d <= 0.9999) it can, and d0 moves on its own."""
    sm = nominal.load("go1")
    feet = [i for i in range(sm.mj.ngeom) if sm.mj.geom_solimp[i, 1] == 1.0]
    assert feet, "the shipped Go1's feet have dmax = 1"
    d0 = sm.mj.geom_solimp[feet, 0].copy()
    soft = nominal.apply(sm, Settings(solimp_dmax=10.0)).mj.geom_solimp
    np.testing.assert_allclose(soft[feet, 1], 1 - 1e-3)
    np.testing.assert_array_equal(soft[feet, 0], d0)  # d0 untouched
    soft = nominal.apply(sm, Settings(solimp_d0=0.5)).mj.geom_solimp
    np.testing.assert_allclose(soft[feet, 0], 1 - (1 - d0) * 0.5)
    assert (soft[feet, 1] == 1.0).all()
    assert "1 - dmax (solimp): x 10" in " ".join(nominal.summary(Settings(solimp_dmax=10.0), sm))
    # the default setting moves both; the factors multiply
    both = nominal.apply(sm, Settings(solimp_softness=2.0, solimp_d0=0.5)).mj.geom_solimp
    np.testing.assert_allclose(both[feet, 0], d0)
    np.testing.assert_allclose(both[feet, 1], 1 - 2e-4)
    assert "solimp_softness" in calibrate.CalibrateConfig().continuous


def test_continuous_fit_starts_from_a_value_off_its_coordinate_grid():
    """A start that does not survive exp(log) bit for bit (a calibrated solref times a folded
    contact_softness) is its own starting point, not a missing cache key."""
    sm = nominal.load("pendulum")
    _, logged = real.generate(sm, {}, 2, 40, seed=1)
    data = fit.make_data(logged, 2)
    scale = diagnose.scale_of(sm, fit.make_data(logged))
    v = 1.3811745813108585
    assert calibrate._from_z("solref_timeconst", calibrate._z("solref_timeconst", v)) != v
    start = Settings(solref_timeconst=v)
    s, loss, _ = calibrate.fit_continuous(sm, start, data, scale, ["solref_timeconst"], 1)
    assert np.isfinite(loss)
    assert s.solref_timeconst == pytest.approx(v)  # no contacts on the pendulum: nothing to gain, the start stays


def test_discrete_and_continuous_settings_in_turns_revisit_a_discrete_pick():
    # a synthetic training loss where the best time step depends on the contact time constant:
    # at the model's own constant the 2 ms step wins, once the constant is fitted 4 ms does.
    # One round keeps 2 ms; the second round's sweep moves to 4 ms and refits the constant.
    c = {0.002: 1.5, 0.004: 1.9}  # each step's best contact time-constant factor
    base = {0.002: 0.3, 0.004: 0.0}
    loss = lambda s: (s.solref_timeconst - c[s.timestep]) ** 2 + base[s.timestep]
    fit_cont = lambda s: (dataclasses.replace(s, solref_timeconst=c[s.timestep]), base[s.timestep])
    values = {"timestep": [0.002, 0.004], "integrator": [], "cone": [], "contacts": [], "foot_condim": [],
              "iterations": []}
    own = {"timestep": 0.002}
    start = Settings(timestep=0.002)
    picks = {}
    for rounds in (1, 2, 3):
        cfg = calibrate.CalibrateConfig(rounds=rounds)
        path = []
        best, ties, cont = calibrate.in_turns(start, values, own, loss, fit_cont, ["solref_timeconst"], cfg, path)
        moves = [(p["setting"], p["round"]) for p in path]
        picks[rounds] = (best.timestep, best.solref_timeconst, cont["rounds"], moves)
    assert picks[1] == (0.002, 1.5, 1, [])
    assert picks[2] == (0.004, 1.9, 2, [("timestep", 1)])
    assert picks[3] == picks[2][:2] + (2, [("timestep", 1)])  # a third sweep moves nothing: the turns stop
    # nothing continuous to fit: one sweep, no record
    best, _, cont = calibrate.in_turns(start, values, own, loss, fit_cont, [], calibrate.CalibrateConfig(), [])
    assert best.timestep == 0.002 and cont == {}


def test_a_second_start_fits_the_contact_first_where_the_discrete_sweep_takes_a_wrong_turn():
    # a synthetic training loss: at the model's own contact time constant (factor 1) the
    # pyramidal cone looks better, so the discrete-first search keeps it; the elliptic cone with
    # its own fitted constant is far better, which only the continuous-first start finds
    opt = {"elliptic": 2.0, "pyramidal": 1.2}
    floor = {"elliptic": 0.01, "pyramidal": 1.0}
    weight = {"elliptic": 50.0, "pyramidal": 1.0}
    cone = lambda s: s.cone or "elliptic"
    loss = lambda s: floor[cone(s)] + weight[cone(s)] * (s.solref_timeconst - opt[cone(s)]) ** 2
    fit_cont = lambda s: (dataclasses.replace(s, solref_timeconst=opt[cone(s)]), floor[cone(s)])
    values = {"timestep": [], "integrator": [], "cone": ["elliptic", "pyramidal"], "contacts": [],
              "foot_condim": [], "iterations": []}
    own, start = {"cone": "elliptic"}, Settings(cone="elliptic")
    runs = {}
    for first in (False, True):
        cfg = calibrate.CalibrateConfig(continuous_first=first)
        best, _, cont, path, search = calibrate.two_starts(start, start, values, own, loss, fit_cont,
                                                           ["solref_timeconst"], cfg)
        runs[first] = (cone(best), best.solref_timeconst, search, [p["setting"] for p in path])
    assert runs[False] == ("pyramidal", 1.2, "discrete first", ["cone"])
    assert runs[True] == ("elliptic", 2.0, "continuous first", [])
    # where the second start finds nothing better, the first search's result stays
    flat = lambda s: floor[cone(s)]  # the constant does not matter: the sweep keeps elliptic
    best, _, _, _, search = calibrate.two_starts(start, start, values, own, flat, fit_cont, ["solref_timeconst"],
                                                 calibrate.CalibrateConfig())
    assert (cone(best), search) == ("elliptic", "discrete first")


def test_a_finer_time_step_must_pay_for_the_replays_it_multiplies():
    # from 2 ms: 1 ms doubles every later replay, so it must lower the loss by 2 x min_gain (2%);
    # from 4 ms, 2 ms likewise; a coarser step needs min_gain alone
    values = {"timestep": [0.001, 0.002, 0.004, 0.005], "integrator": [], "cone": [], "contacts": [],
              "foot_condim": [], "iterations": []}

    def pick(losses, start=0.002, **kw):
        cfg = calibrate.CalibrateConfig(**kw)
        best, _ = calibrate._sweep(Settings(timestep=start), values, {"timestep": start},
                                   lambda s: losses[s.timestep], cfg, [], 0)
        return best.timestep

    losses = {0.001: 0.986, 0.002: 1.0, 0.004: 1.2, 0.005: 1.3}  # 1 ms wins 1.4%: not enough
    assert pick(losses) == 0.002 and pick(losses, step_cost=False) == 0.001
    assert pick(losses | {0.001: 0.975}) == 0.001  # 2.5%: it pays
    assert pick(losses | {0.004: 0.985}) == 0.004  # coarser: 1.5% > min_gain
    coarse = {0.001: 1.1, 0.002: 0.985, 0.004: 1.0, 0.005: 1.1}
    assert pick(coarse, start=0.004) == 0.004 and pick(coarse | {0.002: 0.975}, start=0.004) == 0.002


def test_settings_naming_the_models_own_value_are_one_model():
    own = {"timestep": 0.002, "iterations": 100, "cone": "elliptic"}
    c = calibrate.ByModel(own)
    c[Settings()] = 1.0
    assert Settings(timestep=0.002, iterations=100, cone="elliptic") in c and c.get(Settings(cone="pyramidal")) is None
    # a sweep whose solver cap goes from None to the model's own 100 changes no model: no move, so no
    # second pass re-scores every other setting (the Go1's calibration did, 11-13 replays per pass)
    scored = []

    def loss(s):
        scored.append(calibrate._neutral(s, own))
        return 2.0 if s.cone == "pyramidal" else 1.0

    values = {"timestep": [], "integrator": [], "cone": ["elliptic", "pyramidal"], "contacts": [], "foot_condim": [],
              "iterations": [15, 100]}
    path = []
    best, moved = calibrate._sweep(Settings(cone="elliptic"), values, own, loss, calibrate.CalibrateConfig(), path, 0)
    assert not moved and path == [] and calibrate._neutral(best, own) == Settings()


def test_contact_effect_start_is_adopted_only_where_it_fits_better_held_out(monkeypatch):
    """The second start of the refinement: ground friction (no setting reproduces it) is screened
    on the nominal model and held fixed in a calibration from the start; that calibration is
    adopted only where its held-out gap, with the friction applied, beats the other's by
    ``min_gain``. Stubbed screen and calibrations: the selection rule alone."""
    cfg = calibrate.CalibrateConfig()
    first = calibrate.Calibration(model="first", settings=Settings(impratio=0.07), record={"applied": True})
    alt = calibrate.Calibration(model="alt", settings=Settings(impratio=0.16), record={"applied": True})
    screened = {}
    # the held-out gap each calibration records: the first pass's alone, the second start's with
    # friction applied
    gap_first = lambda g: first.record.update(heldout_gap_calibrated=g)
    gap_alt = lambda g: alt.record.update(heldout_gap_with_held=g)

    def fake_screen(base, *a, only=None, **k):
        screened["only"] = only
        found = screened.get("found", {})
        rows = [{"effect": n, "value": v[0], "loss": screened["loss"]} for n, v in found.items()]
        return found, {"loss_without": 100.0, "screen": rows}

    monkeypatch.setattr(calibrate, "screen", fake_screen)
    monkeypatch.setattr(calibrate, "calibrate", lambda sm, *a, applied=None, **k: alt)
    test = type("T", (), {"k": 3})()
    run = lambda held={}: calibrate._contact_effect_start("sm", first, first, held, None, test, None, cfg, 5,
                                                          QUIET)
    # nothing gains on the nominal model: the first calibration stays, nothing else is run
    cal, info = run()
    assert cal is first and not info["adopted"] and screened["only"] == frozenset({"ground_friction"})
    # friction gains, but closes less than half of the nominal loss on its own: no second start
    screened.update(found={"ground_friction": [0.3]}, loss=72.0)
    gap_first(0.145), gap_alt(0.048)
    cal, info = run()
    assert cal is first and not info["adopted"] and "heldout_gap" not in info
    # it closes 83%: adopted where it fits 3x better held out, kept out where within min_gain
    screened["loss"] = 17.0
    cal, info = run()
    assert cal is alt and info["adopted"] and info["held_fixed"] == {"ground_friction": [0.3]}
    gap_alt(0.145 * (1 - cfg.min_gain / 2))
    cal, info = run()
    assert cal is first and not info["adopted"]
    # a refinement that held friction at another value (screened on top of the first pass): the
    # second start still runs; at the same value it would repeat that refinement and does not
    gap_alt(0.048)
    assert run({"ground_friction": [0.84]})[0] is alt
    cal, info = run({"ground_friction": [0.3]})
    assert cal is first and not info["adopted"] and "heldout_gap" not in info


def test_recheck_fits_the_settings_again_under_the_best_hypothesis_and_adopts_them_where_better():
    """A first calibration that took wrong settings (standing in for one that imitated the effect
    with them) and a refinement that held another effect: with the best hypothesis held fixed,
    the settings go back to the logs' own and the held-out gap drops; a best hypothesis that is the
    refinement's own effect is not checked again."""
    sm = nominal.load("pendulum")
    _, logged = real.generate(sm, {"damping": [0.3]}, 6, 120, seed=2)
    train, test, scale = _split_data(sm, logged, 3)
    wrong = Settings(timestep=0.005, integrator="rk4")
    cal = calibrate.Calibration(model=nominal.apply(sm, wrong), settings=wrong,
                                record={"refined": {"held_fixed": {"armature": [0.05]}}, "changed": ["wrong"]})
    best = {"damping": np.array([0.3])}
    r_now = baseline.residual(cal.model, test, scale, best)
    new, rec = calibrate.recheck(sm, cal, best, r_now, train, test, scale, calibrate.CalibrateConfig(), QUIET)
    assert rec["ran"] and rec["adopted"] and new is not None, rec
    assert new.settings.integrator in (None, "euler") and new.settings.timestep in (None, 0.002), new.settings
    assert rec["heldout_gap"] < 1e-3 * fit.gap(r_now) and rec["p_value"] <= 0.05
    assert new.record["recheck"] == rec and new.record["refined"] == cal.record["refined"]
    same, rec2 = calibrate.recheck(sm, cal, {"armature": np.array([0.05])}, r_now, train, test, scale,
                                   calibrate.CalibrateConfig(), QUIET)
    assert same is None and not rec2["ran"]
    # a gain below the bar is not adopted: here the residual "before" is made only a little worse
    # than the new settings' own
    r_close = baseline.residual(new.model, test, scale, best) * 1.02
    kept, rec3 = calibrate.recheck(sm, cal, best, r_close, train, test, scale, calibrate.CalibrateConfig(), QUIET)
    assert kept is None and rec3["ran"] and not rec3["adopted"], rec3


def test_a_value_that_moves_with_the_rechecked_settings_takes_the_confidence():
    from stride_jax.gap import attribute
    best = {"effects": ["damping"], "params": {"damping": [2.57]}, "param_lo": {"damping": [2.5]},
            "param_hi": {"damping": [2.6]}}
    shift = {"before": {"damping": [1.67]}, "first_settings": ["time step: 2 ms -> 2.5 ms"]}
    (line,) = attribute.settings_shift(best, shift, 0.25)
    assert "1.67 -> 2.57" in line
    assert attribute.settings_shift(best, {"before": {"damping": [2.45]}}, 0.25) == []  # within 25% of 2.57
    assert attribute.settings_shift(best, {"before": {"damping": [2.55]}}, 0.0) == []  # inside the interval
    assert attribute.settings_shift(best, None, 0.25) == []


def test_the_recheck_runs_only_for_a_hypothesis_that_can_name_an_effect():
    cfg = diagnose.PRESETS["tiny"]
    w = lambda params, sig: {"ranking": [{"params": params}], "detection": {"significant": sig},
                             "probe_explained_nominal": 0.0}
    assert diagnose._names_an_effect(w({"damping": [0.3]}, True), cfg)
    assert not diagnose._names_an_effect(w({"damping": [0.3]}, False), cfg)  # no significant gap
    assert not diagnose._names_an_effect(w({"mass@hip": [1.0]}, True), cfg)  # an effect at its nominal value
