"""experiments/validation_variants.py: planner variants' select-learned rows on the same
validation episodes, each against the policy and the first variant, and by command."""

import json

import pytest

COMMANDS = [[[1.0, 0.0, 0.0], [0.2, 0.3, 0.4]], [[0.0, 0.0, 0.0], [0.8, -0.1, 0.0]],
            [[0.3, 0.2, -0.4], [0.9, 0.0, 0.1]]]
CONFIG = dict(robot="g1", policy="p", worlds=3, seconds=2.0, change_s=1.0, settle_s=0.5, seed=0)


def _table(folder, per_world, policy=None, commands=COMMANDS, **config):
    row = dict(label="soft", falls=0, worlds=3, vel_rmse=sum(per_world) / 3, per_world=per_world,
               fell=[False] * 3, per_piece=[[e, e] for e in per_world],
               per_piece_yaw=[[0.1, 0.1]] * 3, code="abc")
    table = dict(command=f"select-learned {folder.name}", code="abc", rows=[row],
                 config=dict(CONFIG, **config), commands=commands,
                 command_bounds=[[0.0, -0.3, -0.5], [1.0, 0.3, 0.5]])
    if policy is not None:
        table["policy"] = dict(label="policy", falls=0, worlds=3, vel_rmse=sum(policy) / 3,
                               per_world=policy, fell=[False] * 3,
                               per_piece=[[e, e] for e in policy], per_piece_yaw=[[0.1, 0.1]] * 3)
    folder.mkdir()
    (folder / "selection.json").write_text(json.dumps(table))
    return folder


def test_variants_are_paired_against_the_policy_and_the_first(tmp_path, experiment):
    mod = experiment("validation_variants")
    policy = [0.06, 0.07, 0.05]
    a = _table(tmp_path / "a", [0.08, 0.10, 0.07], policy=policy)
    b = _table(tmp_path / "b", [0.061, 0.068, 0.052])  # no policy row: read from a's
    out = tmp_path / "v.md"
    mod.main([f"headline={a}", f"no_family={b}", "--out", str(out)])
    res = json.loads(out.with_suffix(".json").read_text())
    head, nofam = res["variants"]
    assert head["vs_first"] is None and head["vs_policy"]["lo"] > 0  # worse than the policy
    assert nofam["vs_policy"]["diff"] == pytest.approx(0.001 / 3 * (1 - 2 + 2), abs=1e-9)
    assert nofam["vs_first"]["hi"] < 0
    assert nofam["where"] and nofam["where"][0]["label"] == "stops (all zero)"
    md = out.read_text()
    assert "| the policy alone | 0 | 0.0600 |" in md and "minus headline" in md


def test_tables_of_other_episodes_are_refused(tmp_path, experiment):
    mod = experiment("validation_variants")
    a = _table(tmp_path / "a", [0.08, 0.1, 0.07], policy=[0.06, 0.07, 0.05])
    other_seed = _table(tmp_path / "s", [0.08, 0.1, 0.07], seed=1)
    other_cmds = _table(tmp_path / "c", [0.08, 0.1, 0.07], commands=COMMANDS[::-1])
    for bad, said in ((other_seed, "seed=1"), (other_cmds, "commands differ")):
        with pytest.raises(SystemExit, match=said):
            mod.main([f"a={a}", f"b={bad}", "--out", str(tmp_path / "v.md")])
    with pytest.raises(SystemExit, match="no select-learned table"):
        mod.main([f"a={tmp_path / 'none'}", "--out", str(tmp_path / "v.md")])
    with pytest.raises(SystemExit, match="no candidate 'x'"):
        mod.main([f"a={a}:x", "--out", str(tmp_path / "v.md")])
