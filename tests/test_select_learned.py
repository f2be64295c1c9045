"""``stride select-learned``: candidate learned reward/value files scored by the closed loop they
serve on the same validation episodes (paired), falls first, then velocity tracking."""

import json
import shutil

import numpy as np
import pytest

from stride_jax import cli
from stride_jax.jobs import select_learned as sel


def test_candidates_plan_the_same_episodes_and_are_ranked(tmp_path, capsys):
    """A copy of a file scores exactly as the file (the same commands, keys and planner: the
    comparison is paired), another file differently; the table ranks by the error and gives
    the paired difference from the best; it shares one compile across candidates of one
    structure."""
    a = "results/learned_go1/reward_value.msgpack"
    b = "results/learned_go1_slope/reward_value.msgpack"
    copy = tmp_path / "copy.msgpack"
    shutil.copy(a, copy)
    out = tmp_path / "sel"
    cli.main(["select-learned", "--preset", "tiny", "--policy", "results/policies/ppo_go1",
              "--model", "onn=results/models/go1/onn-s0", "--worlds", "3",
              "--candidates", f"a={a},copy={copy},b={b}", "--out", str(out)])
    table = json.loads((out / "selection.json").read_text())
    rows = {r["label"]: r for r in table["rows"]}
    assert rows["copy"]["per_world"] == rows["a"]["per_world"]
    assert rows["b"]["per_world"] != rows["a"]["per_world"]
    errs = [r["vel_rmse"] for r in table["rows"]]
    assert errs == sorted(errs) and table["rows"][0]["vs_best"] is None
    other = next(r for r in table["rows"][1:] if r["label"] in ("a", "b") and
                 r["per_world"] != table["rows"][0]["per_world"])
    v = other["vs_best"]
    assert v["n"] == 3 and v["lo"] <= v["diff"] <= v["hi"]
    assert v["diff"] == pytest.approx(np.mean(np.array(other["per_world"])
                                              - np.array(table["rows"][0]["per_world"])))
    md = (out / "selection.md").read_text()
    assert "| 1 |" in md and "| 3 |" in md and "select-learned" in md
    ties = md.split("Not told apart from the best")[1].split(".")[0]
    best = table["rows"][0]["label"]
    if best in ("a", "copy"):  # identical errors are a tie, though they have no interval
        assert ({"a", "copy"} - {best}).pop() in ties
    said = capsys.readouterr().out  # each candidate says what it runs before its episodes
    assert "copy: 3 episodes of 0.1 s side by side" in said and "best: " in said
    assert np.asarray(table["commands"]).shape == (3, 2, 3)  # worlds x changes x command
    ref = table["policy"]  # the policy alone on the same episodes: a reference, never ranked
    assert ref["label"] == "policy" and len(ref["per_world"]) == 3
    assert ref["per_world"] not in [r["per_world"] for r in table["rows"]]
    assert "The policy alone on the same episodes" in md and "the best candidate minus" in md
    # each episode's error under each of its commands, and where the best and the policy differ
    assert np.asarray(rows["a"]["per_piece"], float).shape == (3, 2)
    assert f"Where {best} and the policy differ" in md and "| stops (all zero) |" in md


def test_where_the_best_and_the_policy_differ_is_read_by_command():
    """A planner that loses only under lateral commands shows it in the lateral rows alone."""
    commands = [[[1.5, 0.05, 0.1], [0.2, 0.4, 0.0]], [[0.0, 0.0, 0.0], [1.8, -0.45, 0.2]],
                [[0.3, -0.02, -0.9], [1.2, 0.3, 0.1]]]  # worlds x pieces x (vx, vy, yaw)
    bounds = [[0.0, -0.5, -1.0], [2.0, 0.5, 1.0]]
    policy = dict(per_piece=[[0.05, 0.05], [0.02, 0.05], [0.05, 0.05]],
                  per_piece_yaw=[[0.1, 0.1], [0.1, 0.1], [0.1, 0.1]])
    lateral = [[abs(c[1]) >= 0.25 for c in w] for w in commands]
    noise = [[0.001, -0.002], [0.0, 0.002], [-0.001, 0.001]]
    plan = dict(per_piece=[[p + (0.04 if lat else 0.0) + e for p, lat, e in zip(*z)]
                           for z in zip(policy["per_piece"], lateral, noise)],
                per_piece_yaw=[[0.1, None], [0.1, 0.1], [0.1, 0.1]],  # one piece not scored
                per_piece_forward=[[0.02, 0.0], [0.0, 0.0], [0.0, 0.06]])
    groups = {g["label"]: g for g in sel.by_command(plan, policy, commands, bounds)}
    big, small = groups["lateral 0.25 or more (either sign)"], groups["lateral under 0.25 (either sign)"]
    assert big["n"] == 2 and small["n"] == 2  # the stop is neither; the unscored piece dropped
    assert big["vel"]["lo"] > 0.02 and small["vel"]["hi"] < 0.01
    assert groups["stops (all zero)"]["n"] == 1 and groups["stops (all zero)"]["vel"] is None
    assert "forward" not in big  # the policy's row has no signed offsets
    policy["per_piece_forward"] = [[0.0] * 2] * 3
    fast = {g["label"]: g for g in sel.by_command(plan, policy, commands, bounds)}
    assert fast["forward 1 or more"]["forward"] == pytest.approx([0.08 / 3, 0.0])
    assert sel.by_command(plan, {"per_world": [0.1]}, commands, bounds) == []  # an old row
    assert all("|" not in g for g in groups)  # the labels sit in a markdown table


def test_falls_rank_before_the_error():
    """A candidate whose planner fell in fewer episodes ranks first whatever its error; the
    paired difference reads only the episodes both kept up."""
    rows = [dict(label="low_error_one_fall", falls=1, vel_rmse=0.05, per_world=[0.05, 0.05, 0.9],
                 fell=[False, False, True]),
            dict(label="no_fall", falls=0, vel_rmse=0.07, per_world=[0.06, 0.08, 0.07],
                 fell=[False, False, False])]
    ranked = sel.rank(rows)
    assert [r["label"] for r in ranked] == ["no_fall", "low_error_one_fall"]
    assert ranked[1]["vs_best"]["n"] == 2
    assert ranked[1]["vs_best"]["diff"] == pytest.approx(-0.02)


def test_bad_candidates_are_clear_errors(tmp_path):
    with pytest.raises(ValueError, match="not LABEL=PATH"):
        sel.SelectConfig(candidates="just_a_path.msgpack")
    with pytest.raises(ValueError, match="labels repeat"):
        sel.SelectConfig(candidates="a=x.msgpack,a=y.msgpack")
    with pytest.raises(ValueError, match="NAME=RUN"):
        sel.SelectConfig(candidates="a=x", model="stride")
    with pytest.raises(ValueError, match="at least one"):
        sel.run(sel.SelectConfig())
    with pytest.raises(FileNotFoundError, match="candidate b"):
        sel.run(sel.SelectConfig(candidates=f"a=results/learned_go1/reward_value.msgpack,"
                                            f"b={tmp_path / 'missing.msgpack'}"))


def test_a_second_run_plans_only_the_new_candidates(tmp_path, capsys):
    """The table is written after each candidate; the same settings and out again keep the rows
    there (a cut call resumes) and plan only what is new, or a file whose content changed; other
    settings on the same out are a clear error, not a mixed table."""
    a = "results/learned_go1/reward_value.msgpack"
    b = tmp_path / "b.msgpack"
    shutil.copy("results/learned_go1_slope/reward_value.msgpack", b)
    out = tmp_path / "sel"
    base = ["select-learned", "--preset", "tiny", "--policy", "results/policies/ppo_go1",
            "--model", "onn=results/models/go1/onn-s0", "--out", str(out)]
    cli.main(base + ["--candidates", f"a={a}"])
    saved = json.loads((out / "selection.json").read_text())
    first = saved["rows"][0]
    # a table written before a setting was added resumes with that setting at its default
    del saved["config"]["policy_reference"]
    (out / "selection.json").write_text(json.dumps(saved))
    capsys.readouterr()
    cli.main(base + ["--candidates", f"a={a},b={b}"])
    said = capsys.readouterr().out
    assert "a planned already; kept" in said and "a: 2 episodes" not in said
    assert "the policy alone" not in said  # its reference row kept too
    assert "b: 2 episodes" in said
    rows = {r["label"]: r for r in json.loads((out / "selection.json").read_text())["rows"]}
    assert rows["a"]["per_world"] == first["per_world"] and rows["a"]["seconds"] == first["seconds"]
    assert rows["a"]["code"] == first["code"]  # each row keeps the code that planned it
    shutil.copy(a, b)  # b's content changes: planned again, now as a
    cli.main(base + ["--candidates", f"a={a},b={b}"])
    said = capsys.readouterr().out
    assert "b: 2 episodes" in said and "a: 2 episodes" not in said
    rows = {r["label"]: r for r in json.loads((out / "selection.json").read_text())["rows"]}
    assert rows["b"]["per_world"] == rows["a"]["per_world"]
    with pytest.raises(SystemExit, match=r"other settings \(worlds differ\)"):
        cli.main(base + ["--candidates", f"a={a}", "--worlds", "3"])


def test_an_unfinished_table_says_so():
    row = dict(label="a", path="x", falls=0, worlds=2, vel_rmse=0.1, per_world=[0.1, 0.1],
               fell=[False, False], vs_best=None)
    table = dict(command="c", code="k", candidates=3, rows=[row],
                 config=dict(worlds=2, seconds=1.0, change_s=0.5, model="m", policy="p"))
    assert "1 of 3 candidates planned so far" in sel.markdown(table)
    assert "so far" not in sel.markdown({**table, "candidates": 1})


def test_the_table_names_the_candidates_not_told_apart_from_the_best():
    def row(label, falls, lo, hi):
        return dict(label=label, path="x", falls=falls, worlds=4, vel_rmse=0.1,
                    per_world=[0.1] * 4, fell=[False] * 4,
                    vs_best=None if lo is None else dict(diff=(lo + hi) / 2, lo=lo, hi=hi, n=4))
    rows = [row("best", 0, None, None), row("tie", 0, -0.01, 0.02), row("worse", 0, 0.01, 0.03),
            row("fell_once", 1, -0.02, 0.01)]
    table = dict(command="c", code="k", candidates=4, rows=rows,
                 config=dict(worlds=4, seconds=1.0, change_s=0.5, model="m", policy="p"))
    assert "Not told apart from the best (best): tie." in sel.markdown(table)
    assert "(best): none." in sel.markdown({**table, "rows": rows[:1]})


def test_the_closed_loops_model_options_reach_the_planner(tmp_path):
    """--model-substeps, --sensor-noise (and the error model, precision) are the closed loop's:
    each changes what the same candidate's planner does on the same episodes; the oracle takes
    no learned model's options, and sensor terms without their factor are an error."""
    from stride_jax.control import episode
    from stride_jax.sim import model as sim_model

    sm = sim_model.load("go1")
    q, qd = sm.mj.qpos0.copy(), np.zeros(sm.mj.nv)
    q[2] += 0.05
    ctrl = np.zeros(sm.mj.nu)
    run, onn = "results/models/go1/stride-s0", "results/models/go1/onn-s0"
    as_trained = episode.learned_step_fn(run, sm)(q, qd, ctrl, None)
    coarse = episode.learned_step_fn(run, sm, substeps=1)(q, qd, ctrl, None)
    assert not np.allclose(as_trained[1], coarse[1])  # one substep: a coarser integration
    np.testing.assert_array_equal(  # a next-observation model predicts the period at once
        episode.learned_step_fn(onn, sm)(q, qd, ctrl, None)[1],
        episode.learned_step_fn(onn, sm, substeps=1)(q, qd, ctrl, None)[1])
    a = "results/learned_go1/reward_value.msgpack"
    base = ["select-learned", "--preset", "tiny", "--policy", "results/policies/ppo_go1",
            "--model", f"stride={run}", "--candidates", f"a={a}", "--no-policy-reference"]
    cli.main(base + ["--out", str(tmp_path / "plain")])
    cli.main(base + ["--sensor-noise", "1", "--out", str(tmp_path / "noisy")])
    plain, noisy = (json.loads((tmp_path / d / "selection.json").read_text())
                    for d in ("plain", "noisy"))
    assert noisy["config"]["sensor_noise"] == 1.0 and plain["policy"] is None
    assert noisy["rows"][0]["per_world"] != plain["rows"][0]["per_world"]
    with pytest.raises(ValueError, match="oracle plans through the simulator"):
        sel.SelectConfig(model="oracle", model_substeps=2)
    with pytest.raises(ValueError, match="--sensor-noise is 0"):
        sel.SelectConfig(sensors=sel.SensorNoise(gyro_std=1.0))
    with pytest.raises(ValueError, match="model_substeps=-1"):
        sel.SelectConfig(model_substeps=-1)
