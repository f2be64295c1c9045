"""The independent benchmark: its "real" robot is written apart from the diagnosis's effect code,
with simulator settings that differ from the nominal model; the tiny preset runs end to end."""

import ast
import copy
import dataclasses
import json
import pathlib

import mujoco
import numpy as np
import pytest

from stride_jax import robots
from stride_jax.jobs import gap_bench_independent as bi
from stride_jax.jobs import gap_bench_real as gen
from stride_jax.jobs import gap as cli


def test_the_generator_does_not_import_the_effect_code_the_diagnosis_fits():
    tree = ast.parse(pathlib.Path(gen.__file__).read_text())
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            names |= {f"{node.module}.{a.name}" for a in node.names} | {node.module}
        elif isinstance(node, ast.Import):
            names |= {a.name for a in node.names}
    for banned in ("stride_jax.gap.effects", "stride_jax.gap.sim", "stride_jax.gap.real"):
        assert banned not in names, banned
    src = pathlib.Path(gen.__file__).read_text()
    assert "effects." not in src and "real.generate" not in src


def test_drawn_settings_differ_from_the_model_and_planting_edits_what_it_says():
    robot = robots.get("go1")
    m0 = gen.robot_spec("go1").compile()
    rng = np.random.default_rng(0)
    for _ in range(20):
        s = gen.draw_settings(m0, rng, robot.ctrl_dt)
        assert s, "at least one setting differs"
        m = copy.copy(m0)
        gen.set_simulator(m, s, [g for f in robot.feet for g in f.geoms])
        n = robot.ctrl_dt / m.opt.timestep
        assert abs(n - round(n)) < 1e-9
        if s.get("feet_only"):
            assert ((m.geom_contype != 0) | (m.geom_conaffinity != 0)).sum() == 5
    m = copy.copy(m0)
    ctl = gen.plant(m, {"damping@calf": 2.0, "delay": 0.01, "payload": 1.0}, robot.joints, robot.base_body)
    calf = [m.jnt_dofadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, j)] for j in robot.joints if "calf" in j]
    hip = [m.jnt_dofadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, j)] for j in robot.joints if "hip" in j]
    assert np.allclose(m.dof_damping[calf] - m0.dof_damping[calf], 2.0)
    assert np.allclose(m.dof_damping[hip], m0.dof_damping[hip])
    assert ctl.delay_steps == 5 and ctl.deadband == 0.0  # 10 ms at the shipped 2 ms step
    trunk = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "trunk")
    assert m.body_mass[trunk] - m0.body_mass[trunk] == 1.0


def test_joint_and_actuator_effects_plant_on_the_joints_named_only():
    robot = robots.get("go1")
    m0 = gen.robot_spec("go1").compile()
    m = copy.copy(m0)
    gen.plant(m, {"kp_scale@FR_": 0.6, "torque_limit@thigh": 0.5, "frictionloss@hip": 0.3}, robot.joints,
              robot.base_body)
    names = [mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_JOINT, m.actuator_trnid[a, 0]) for a in range(m.nu)]
    fr = np.array(["FR_" in n for n in names])
    thigh = np.array(["thigh" in n for n in names])
    assert fr.sum() == 3 and thigh.sum() == 4
    assert np.allclose(m.actuator_gainprm[fr, 0], 0.6 * m0.actuator_gainprm[fr, 0])
    assert np.allclose(m.actuator_gainprm[~fr, 0], m0.actuator_gainprm[~fr, 0])
    assert np.allclose(m.actuator_forcerange[thigh], 0.5 * m0.actuator_forcerange[thigh])
    assert np.allclose(m.actuator_forcerange[~thigh], m0.actuator_forcerange[~thigh])
    dof = {j: m.jnt_dofadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, j)] for j in robot.joints}
    assert all(np.isclose(m.dof_frictionloss[d] - m0.dof_frictionloss[d], 0.3 if "hip" in j else 0.0)
               for j, d in dof.items())
    for bad, why in (({"damping@wrist": 1.0}, "no joint"), ({"payload@calf": 1.0}, "take a joint part")):
        with pytest.raises(ValueError, match=why):
            gen.plant(copy.copy(m0), bad, robot.joints, robot.base_body)


def test_controls_are_cases_of_their_own_draws_and_keep_the_other_cases_draws():
    cfg = bi.PRESETS["default"]
    many = dataclasses.replace(cfg, controls=3)
    assert [c["kind"] for c in bi.cases(many)[:4]] == ["control"] * 3 + ["single"]
    assert bi.cases(many)[3:] == bi.cases(cfg)[1:]
    assert bi.PRESETS["controls"].controls > 1 and {c["kind"] for c in bi.cases(bi.PRESETS["controls"])} == {"control"}
    # each control index draws its own simulator settings
    robot, m0 = robots.get("go1"), gen.robot_spec("go1").compile()
    draws = [gen.draw_settings(m0, np.random.default_rng([cfg.seed, i]), robot.ctrl_dt) for i in range(3)]
    assert draws[0] != draws[1] != draws[2]
    try:
        bi.cases(dataclasses.replace(cfg, controls=0))
    except ValueError as err:
        assert "controls" in str(err)
    else:
        raise AssertionError("no error for zero controls")


def test_tiny_preset_end_to_end(tmp_path):
    assert cli.main(["bench-independent", "--preset", "tiny", "--out", str(tmp_path)]) == 0
    name = bi.PRESETS["tiny"].name
    res = json.loads((tmp_path / f"{name}.json").read_text())
    for key in ("top1_single", "top1_pairs", "median_shrink_single", "confident_false", "control_verdict"):
        assert key in res and "noise_free" in res[key]
    assert res["confident_false"]["noise_free"] == 0
    assert res["top1_single"]["noise_free"] == 1.0
    # the control names the drawn model-form difference
    (ctrl,) = [r for r in res["cases"] if r["kind"] == "control"]
    assert ctrl["calibration"] and ctrl["verdict"] == "no significant gap"
    assert "simulator settings found" in res["control_verdict"]["noise_free"][0]
    assert ctrl["detection"]["significant"] is False and ctrl["detection"]["rule"] == "detection"
    assert ctrl["detection"]["p_value"] >= ctrl["detection"]["level"]
    summ = res["summary"]["noise_free"]
    assert (summ["controls_detected"], summ["controls_named"], summ["controls"]) == (0, 0, 1)
    (single,) = [r for r in res["cases"] if r["kind"] == "single"]
    assert single["shrink_ratio"] > 0.8 and single["clean"]["shrink_vs_nominal"] > 0.9
    assert (tmp_path / f"{name}.md").read_text().startswith("# Sim-to-real gap: independent benchmark")


def test_a_confident_call_naming_part_of_a_pair_is_false_only_where_the_pair_is_nameable():
    from stride_jax.jobs import gap_bench_score as sc
    pair = {"kind": "pair", "planted": {"payload": [2.0], "torque_scale": [0.8]}, "confident": True}
    assert sc.confident_false(pair | {"named": ["torque_scale"], "nameable": False}) == (False, True)
    assert sc.confident_false(pair | {"named": ["torque_scale"], "nameable": True}) == (True, False)
    assert sc.confident_false(pair | {"named": ["torque_scale", "damping"], "nameable": False}) == (True, False)
    assert sc.confident_false(pair | {"named": ["payload", "torque_scale"], "nameable": True}) == (False, False)
    assert sc.confident_false(pair | {"named": ["torque_scale"], "nameable": False, "confident": False}) == (False, False)
    ool = {"kind": "out_of_library", "planted": {"joint_stiffness": [10.0]}, "confident": True, "named": ["damping"]}
    assert sc.confident_false(ool) == (True, False)


def test_ranked_first_counts_the_best_hypothesis_whatever_the_verdict():
    from stride_jax.jobs import gap_bench_score as sc
    base = {"kind": "single", "planted": {"frictionloss": [0.8]}, "named": [], "confident": False,
            "correct": False, "correct_strict": False, "correct_as_set": False, "noisy": True,
            "verdict": "unexplained by the library"}
    ranked = base | {"best": {"effects": ["frictionloss"]}}
    wrong = base | {"best": {"effects": ["damping"]}}
    silent = base | {"verdict": "no significant gap"}  # nothing ranked
    pair = base | {"kind": "pair", "planted": {"payload": [2.0], "torque_scale": [0.8]},
                   "best": {"effects": ["torque_scale", "payload"]}}  # order aside
    assert [sc.ranked_first(r) for r in (ranked, wrong, silent, pair)] == [True, False, False, True]
    summ = sc.summary([ranked, wrong, silent, pair])["noisy"]
    assert summ["ranked_first_single"] == 1 / 3 and summ["ranked_first_pairs"] == 1.0
    assert summ["top1_single"] == 0.0  # the verdicts named nothing


def test_a_pair_row_is_scored_with_what_each_planted_effect_adds_last():
    # the scorer's pair path (the Go1 preset's pairs) on the pendulum: damping 0.3 under a 20 ms
    # delay, the tiny diagnosis with pairs on; what each effect adds last, at its planted value and
    # against the other re-fitted alone, decides whether the logs can show the pair at all
    from stride_jax.jobs import gap_bench_score as sc
    cfg = dataclasses.replace(bi.PRESETS["tiny"], singles=(), pairs=((("damping", 0.3), ("delay", 0.02)),),
                              pairs_of=-1)
    row, _ = bi.diagnose_case(cfg, 1, False)
    c = row["clean"]
    assert row["kind"] == "pair" and set(row["planted"]) == {"damping", "delay"}
    assert set(c["truth_adds_last"]) == set(c["truth_adds_last_refit"]) == {"damping", "delay"}
    adds = list(c["truth_adds_last"].values()) + list(c["truth_adds_last_refit"].values())
    assert row["nameable"] == (c["truth_closes"] >= 0.5 and min(adds) >= 0.05)
    assert (row["confident_false"], row["confident_partial"]) == sc.confident_false(row)
    summ = sc.summary([row])["noise_free"]
    assert summ["pairs_not_nameable"] == ([] if row["nameable"] else ["damping+delay"])
    assert summ["top1_pairs"] == float(row["correct"])
