"""Finer effects: groups from the kinematic tree, per-group effects, encoder offsets, the finer
choice by held-out margin, indistinguishable sets, the screen against the full path, progress."""

import dataclasses

import numpy as np
import pytest

from stride_jax.gap import calibrate, diagnose, effects, filters, finer, fit, groups, real, replay, screen
from stride_jax.sim import model

# Two position-servo arms on a fixed torso: families type (shoulder, elbow) and limb (left, right).
ARMS = """
<mujoco model="arms">
  <compiler angle="radian"/>
  <option timestep="0.002"/>
  <default><joint type="hinge" axis="1 0 0" range="-1.5 1.5" damping="1" armature="0.02"/></default>
  <worldbody>
    <body name="torso" pos="0 0 1">
      <geom type="box" size="0.1 0.1 0.2" mass="5"/>
      <body name="left_upper" pos="0 0.12 0.15">
        <joint name="left_shoulder_joint"/>
        <geom type="capsule" fromto="0 0 0 0 0.3 0" size="0.03" mass="1"/>
        <body name="left_fore" pos="0 0.3 0">
          <joint name="left_elbow_joint"/>
          <geom type="capsule" fromto="0 0 0 0 0.25 0" size="0.025" mass="0.6"/>
        </body>
      </body>
      <body name="right_upper" pos="0 -0.12 0.15">
        <joint name="right_shoulder_joint"/>
        <geom type="capsule" fromto="0 0 0 0 -0.3 0" size="0.03" mass="1"/>
        <body name="right_fore" pos="0 -0.3 0">
          <joint name="right_elbow_joint"/>
          <geom type="capsule" fromto="0 0 0 0 -0.25 0" size="0.025" mass="0.6"/>
        </body>
      </body>
    </body>
  </worldbody>
  <actuator>
    <position joint="left_shoulder_joint" kp="40" ctrlrange="-1.5 1.5"/>
    <position joint="left_elbow_joint" kp="20" ctrlrange="-1.5 1.5"/>
    <position joint="right_shoulder_joint" kp="40" ctrlrange="-1.5 1.5"/>
    <position joint="right_elbow_joint" kp="20" ctrlrange="-1.5 1.5"/>
  </actuator>
</mujoco>
"""


_NO_CAL = calibrate.CalibrateConfig(mode="off")


@pytest.fixture(scope="module")
def arms(tmp_path_factory):
    path = tmp_path_factory.mktemp("arms") / "arms.xml"
    path.write_text(ARMS)
    return model.load(str(path))


def _quiet(**kw):
    # clean logs need no cleaning: the spike filter's false positives would be a gap of their own;
    # the logs come from the nominal simulator, so the simulator's settings are not calibrated
    # (calibration can take part of a damping as an integrator change: tests/test_gap_calibrate.py)
    return dataclasses.replace(diagnose.PRESETS["tiny"], progress=False, calibrate=_NO_CAL,
                               preprocess=filters.Preprocess(outliers=False), **kw)


def _diagnose(sm, applied, cfg=None, seed=1, n=5, steps=100):
    _, logged = real.generate(sm, applied, n, steps, seed=seed)
    return diagnose.diagnose(sm, logged, cfg or _quiet(), log=lambda s: None)


def test_groups_from_the_tree_and_names(arms, go1, g1):
    g = groups.of(go1)
    assert g.families["type"] == {"hip": (0, 3, 6, 9), "thigh": (1, 4, 7, 10), "calf": (2, 5, 8, 11)}
    assert set(g.families["limb"]) == {"FR", "FL", "RR", "RL"}
    assert g.families["side"]["left"] == (3, 4, 5, 9, 10, 11) and g.families["end"]["front"] == (0, 1, 2, 3, 4, 5)
    assert [go1.mj.body(b).name for b in g.bodies["calf"]] == ["FR_calf", "FL_calf", "RR_calf", "RL_calf"]
    h = groups.of(g1)  # a humanoid: legs, waist and arms; no front/rear; the waist has no side
    assert set(h.families["limb"]) == {"left_leg", "right_leg", "waist", "left_arm", "right_arm"}
    assert "end" not in h.families and "knee" in h.families["type"]
    assert not {12, 13, 14} & set(h.families["side"]["left"] + h.families["side"]["right"])
    a = groups.of(arms)  # an MJCF the project has never seen; the left limb is also the left side
    assert a.families["type"] == {"shoulder": (0, 2), "elbow": (1, 3)}
    assert a.families["limb"] == {"left": (0, 1), "right": (2, 3)} and "side" not in a.families
    assert a.bodies["base"] == ()  # a fixed torso's mass does nothing
    with pytest.raises(KeyError, match="no joint group 'calf'"):
        a.joint_index("calf")


def test_finer_effects_nominal_exact_and_active(go1):
    _, tr = real.generate(go1, {}, 2, 25, seed=0)
    data, scale = fit.make_data(tr, 2), np.ones(go1.mj.nv)
    names = finer.candidates(go1)
    assert {"damping@calf", "kp_scale@FR", "encoder_offset@RL_calf_joint", "mass@thigh", "base_wrench",
            "servo_damping", "torque_limit@rear"} <= set(names)
    nominal = [effects.build(go1, {n: np.asarray(effects.ALL[n].nominal)}) for n in names]
    moved = []
    for n in names:
        e = effects.ALL[n]
        lo, hi = e.bounds(go1)
        nom = np.asarray(e.nominal, float)
        moved.append(effects.build(go1, {n: np.where(hi - nom > nom - lo, nom + 0.5 * (hi - nom), nom - 0.5 * (nom - lo))}))
    r0 = fit.residual(go1, effects.build(go1), data, scale)
    R = replay.residuals(go1, [effects.build(go1)] + nominal + moved, data, scale)
    assert np.array_equal(R[0], r0)  # the batched replay is the one-plan replay, bit for bit
    assert np.array_equal(replay.residuals(go1, [moved[0]], data, scale)[0], fit.residual(go1, moved[0], data, scale))
    for i, n in enumerate(names):
        assert np.array_equal(R[1 + i], r0), n
        assert np.abs(R[1 + len(names) + i] - r0).max() > 1e-3, n
    assert "stiffness@calf" not in effects.ALL and "damping@" not in effects.ALL
    with pytest.raises(ValueError, match="does not apply to robot"):
        effects.build(go1, {"damping@nowhere": [0.1]})


def test_finer_variant_only_when_the_effect_is_on_one_group(arms):
    one = _diagnose(arms, {"damping@elbow": 0.6})
    assert one["verdict"]["effects"] == ["damping@elbow"], one["verdict"]
    row = one["which"]["ranking"][0]
    assert row["vs_all_joints"]["preferred"] and row["vs_all_joints"]["fraction_of_left"] >= 0.1
    assert abs(row["params"]["damping@elbow"][0] - 0.6) < 0.06
    every = _diagnose(arms, {"damping": 0.6})
    assert every["verdict"]["effects"] == ["damping"], every["verdict"]
    finer_rows = [r for r in every["which"]["ranking"] if "vs_all_joints" in r]
    assert finer_rows and not any(r["vs_all_joints"]["preferred"] for r in finer_rows)


def test_encoder_offset_recovered(arms):
    out = _diagnose(arms, {"encoder_offset@left_elbow_joint": 0.05})
    assert out["verdict"]["effects"] == ["encoder_offset@left_elbow_joint"], out["verdict"]
    p = out["which"]["ranking"][0]["params"]["encoder_offset@left_elbow_joint"][0]
    assert abs(p - 0.05) < 0.002


def test_gain_and_motor_constant_are_one_indistinguishable_set(arms):
    # no servo damping and no force limit: a servo gain error and a motor-constant error are the
    # same dynamics, so the report names both as one set, with the reason
    out = _diagnose(arms, {"kp_scale": 0.8})
    v = out["verdict"]
    s = v["indistinguishable_set"]
    assert s is not None and {"kp_scale", "torque_scale"} <= set(s["effects"]), v
    assert set(v["effects"]) <= {"kp_scale", "torque_scale"}
    assert "collinear sensitivity" in s["reasons"][({"kp_scale", "torque_scale"} - set(v["effects"])).pop()]
    assert "indistinguishable set" in v["reason"]


def test_speed_path_gives_the_full_paths_verdict(capsys):
    # a pair, one effect masked by the other: the screen's joint linear fit proposes it, as the
    # full path's conditional grid screen does
    sm = model.load("pendulum")
    _, logged = real.generate(sm, {"damping": 0.3, "delay": 2}, 6, 120, seed=1)
    fast = diagnose.diagnose(sm, logged, dataclasses.replace(diagnose.PRESETS["tiny"], calibrate=_NO_CAL),
                             log=lambda s: None)
    err = capsys.readouterr().err
    assert "screen: replay every candidate" in err and "fits: each shortlisted effect alone" in err
    assert "fits: pairs" in err and "100%" in err
    full = diagnose.diagnose(sm, logged, _quiet(screen=screen.ScreenConfig(shortlist=0)), log=lambda s: None)
    assert capsys.readouterr().err == ""  # progress off
    assert full["screen"] is None and fast["screen"]["shortlist"]
    assert len(full["which"]["ranking"]) > len(fast["which"]["ranking"])
    assert set(fast["verdict"]["effects"]) == {"damping", "delay"}
    for k in ("verdict", "effects", "confident"):
        assert fast["verdict"][k] == full["verdict"][k], (fast["verdict"], full["verdict"])


def test_a_pair_s_indistinguishable_set_swaps_the_collinear_member():
    # servo damping and joint damping are one dynamics without measured torques: a pair named
    # with one of them has the pair with the other as its twin (not the other alone)
    from stride_jax.gap import granularity
    w = {"ranking": [{"effects": ["servo_damping", "torque_limit"], "explained": 0.9}]}
    s = granularity.indistinguishable(w, {"servo_damping": {"damping": 0.98}, "torque_limit": {}}, 0.05)
    assert s["effects"] == ["servo_damping+torque_limit", "damping+torque_limit"]
    single = {"ranking": [{"effects": ["kp_scale"], "explained": 0.9}]}
    assert granularity.indistinguishable(single, {"kp_scale": {"torque_scale": 0.99}}, 0.05)["effects"] == [
        "kp_scale", "torque_scale"]


def test_window_caps_thin_long_logs_and_keep_the_verdict():
    # minutes of logs cost what ~1000 windows cost: the screen's and the fits' strides grow past
    # their caps; capped far below this log's ~470 training windows, the verdict is the same
    assert screen.fit_stride_of(screen.ScreenConfig(), 800) == 1  # the benchmarks' logs: every window
    assert screen.fit_stride_of(screen.ScreenConfig(), 3160) == 4  # 12 x 8 s of Go1 logs
    assert screen.fit_stride_of(screen.ScreenConfig(fit_stride=5), 3160) == 5
    assert screen.fit_stride_of(screen.ScreenConfig(fit_windows=0), 10 ** 6) == 1
    sm = model.load("pendulum")
    _, logged = real.generate(sm, {"damping": 0.3}, 6, 120, seed=2)
    out = {}
    for name, cfg in (("uncapped", screen.ScreenConfig(windows=0, fit_windows=0)),
                      ("capped", screen.ScreenConfig(windows=40, fit_windows=100))):
        out[name] = diagnose.diagnose(sm, logged, _quiet(screen=cfg), log=lambda s: None)
    n_tr, _ = out["capped"]["screen"]["windows"]
    assert n_tr <= 40 < out["uncapped"]["screen"]["windows"][0]
    assert out["capped"]["which"]["fit_windows"] <= 100 < out["uncapped"]["which"]["fit_windows"]
    assert out["uncapped"]["which"]["fit_stride"] == 1 < out["capped"]["which"]["fit_stride"]
    for k in ("verdict", "effects"):
        assert out["capped"]["verdict"][k] == out["uncapped"]["verdict"][k] == (
            "explained" if k == "verdict" else ["damping"])
    assert out["capped"]["which"]["ranking"][0]["params"]["damping"][0] == pytest.approx(0.3, abs=0.03)
    # intervals: the named single has one around its estimate; singles that cannot be named
    # (below the best two held out) were fitted without
    ranking = out["uncapped"]["which"]["ranking"]
    top = ranking[0]
    assert top["interval"] and top["param_lo"]["damping"][0] < top["params"]["damping"][0] < top["param_hi"]["damping"][0]
    singles = sorted((r for r in ranking if len(r["effects"]) == 1), key=lambda r: -r["explained"])
    assert len(singles) > 2 and not any(r["interval"] for r in singles[2:] if r is not top)


def test_a_side_or_end_of_a_quadruped_adds_up_its_limbs_columns(go1, g1, monkeypatch):
    names = screen.candidate_names(go1, screen.ScreenConfig())
    u = finer.unions(go1, names)
    assert u["damping@left"] == ("damping@FL", "damping@RL") and u["kp_scale@front"] == ("kp_scale@FR", "kp_scale@FL")
    assert {n.partition("@")[2] for n in u} == {"left", "right", "front", "rear"} and len(u) == 24
    assert set(finer.unions(g1, screen.candidate_names(g1, screen.ScreenConfig()))) == {
        f"{b}@{s}" for b in ("damping", "frictionloss", "armature", "kp_scale", "torque_limit", "servo_damping")
        for s in ("left", "right")}  # a humanoid's sides: its leg and its arm
    _, tr = real.generate(go1, {}, 2, 40, seed=3)
    data = fit.make_data(tr, 2)
    scale = diagnose.scale_of(go1, data)
    rows = np.arange(len(data.start))
    cfg = screen.ScreenConfig()
    plans = []
    many = replay.residuals
    monkeypatch.setattr(replay, "residuals", lambda sm, p, *a, **k: plans.append(len(p)) or many(sm, p, *a, **k))
    group = ["damping@FR", "damping@FL", "damping@RR", "damping@RL", "damping@left", "torque_limit@FL",
             "torque_limit@RL", "torque_limit@left"]
    C = screen.columns(go1, group, data, scale, cfg, rows, show=False)
    assert plans == [7]  # the nominal and six limbs, no replay of the sides
    for side in ("damping@left", "torque_limit@left"):
        D = screen.columns(go1, [side], data, scale, cfg, rows, show=False)  # replayed itself
        a, b = C.J_tr[C.cols(side)[0]].ravel(), D.J_tr[0].ravel()
        assert a @ b / (np.linalg.norm(a) * np.linalg.norm(b)) > 0.95, side  # the same to first order
        assert np.linalg.norm(a - b) < 0.3 * np.linalg.norm(b), side


def test_the_screen_scores_candidates_by_cross_validation_over_training_trajectories():
    # an effect with several parameters fits the training windows' noise; out of sample it gains
    # nothing: the cross-validated score ranks the planted damping first, the 3-vector below zero
    sm = model.load("pendulum")
    _, logged = real.generate(sm, {"damping": 0.3}, 4, 80, seed=6, noise=real.SensorNoise())
    train = fit.make_data(logged, 2)
    scale = diagnose.scale_of(sm, fit.make_data(logged))
    rows = screen.rows_every(train, 1)
    names = [e.name for e in effects.candidates(sm)]
    C = screen.columns(sm, names, train, scale, screen.ScreenConfig(), rows, show=False)
    assert sorted(set(C.fold)) == [0, 1, 2, 3] and len(C.fold) == len(rows)  # one fold per trajectory
    two = fit.make_data(logged[:2], 2)
    assert len(set(screen.folds(two, np.arange(len(two.start))))) == 8  # two trajectories: their quarters
    fits = {n: screen.linear_fit(C, sm, (n,)) for n in names}
    for n, (_, left_train, left_cv) in fits.items():
        assert left_train <= left_cv + 1e-9, n  # in sample never looks worse than out of sample here
    assert min(fits, key=lambda n: fits[n][2]) == "damping"
    assert fits["damping"][0]["damping"][0] == pytest.approx(0.3, abs=0.06)
    assert fits["com_offset"][2] > 1.0 > fits["com_offset"][1]  # worse than nothing out of sample


def test_the_one_step_check_replays_at_most_two_members_of_one_effect(arms):
    _, logged = real.generate(arms, {"damping@left": 0.8}, 4, 60, seed=4)
    train, test = fit.make_data(logged[:3], 2), fit.make_data(logged[3:], 2)
    scale = diagnose.scale_of(arms, fit.make_data(logged))
    out = screen.run(arms, train, test, scale, screen.ScreenConfig(check=5), 0.005, show=False, log=lambda s: None)
    checked = [r["effect"] for r in out["table"] if "checked_heldout" in r]
    families = [finer.parent(n) for n in checked]
    assert len(checked) == 5 and max(families.count(f) for f in families) == screen.CHECK_PER_EFFECT
    assert finer.parent(out["table"][0]["effect"]) == "damping"


def test_the_refinements_screen_holds_a_joint_group_where_the_logs_carry_one(arms):
    # damping mostly on the elbows: the all-joints damping also lowers the training loss, less; the
    # settings refitted with it held would make up for the rest (the speed case's recheck)
    _, logged = real.generate(arms, {"damping@elbow": 0.6, "damping@shoulder": 0.05}, 4, 100, seed=3)
    train = fit.make_data(logged, 2)
    scale = diagnose.scale_of(arms, fit.make_data(logged))
    cfg = calibrate.CalibrateConfig()
    held, rec = calibrate.screen(arms, train, scale, cfg, grid=5)
    assert list(held) == ["damping@elbow"], rec["screen"][:4]
    assert abs(held["damping@elbow"][0] - 0.6) < 0.1
    names = [r["effect"] for r in rec["screen"]]
    assert "damping" in names and names.index("damping") > names.index("damping@elbow")
    coarse, rec0 = calibrate.screen(arms, train, scale, dataclasses.replace(cfg, refine_finer=0), grid=5)
    assert list(coarse) == ["damping"] and not any("@" in r["effect"] for r in rec0["screen"])
    loss = {r["effect"]: r["loss"] for r in rec["screen"]}
    ratio = loss["damping@elbow"] / loss["damping"]  # the margin rule at its edge, both sides
    assert ratio < 0.9 and "group_not_held" not in rec
    strict, rec1 = calibrate.screen(arms, train, scale, dataclasses.replace(cfg, refine_finer_margin=1 - ratio / 2),
                                    grid=5)
    assert list(strict) == ["damping"] and rec1["group_not_held"]["group"] == "damping@elbow"
    held2, _ = calibrate.screen(arms, train, scale, dataclasses.replace(cfg, refine_finer_margin=1 - ratio * 2), grid=5)
    assert list(held2) == ["damping@elbow"]
    only, _ = calibrate.screen(arms, train, scale, cfg, grid=5, only=frozenset({"damping"}))
    assert list(only) == ["damping"]  # ``only`` screens what it names, no groups
    assert finer.children(arms, "damping") == ["damping@shoulder", "damping@elbow", "damping@left",
                                               "damping@right"]
    assert finer.children(arms, "payload") == [] and finer.children(arms, "damping@elbow") == []
    with pytest.raises(ValueError, match="refine_finer"):
        calibrate.CalibrateConfig(refine_finer=-1)
    with pytest.raises(ValueError, match="refine_finer_margin"):
        calibrate.CalibrateConfig(refine_finer_margin=1.0)
