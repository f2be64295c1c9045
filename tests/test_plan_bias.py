"""experiments/plan_bias.py: the planner's replays (model against simulator) read by command."""

import numpy as np
import pytest

BOUNDS = [[0.0, -0.3, -0.5], [1.0, 0.3, 0.5]]
COMMANDS = np.array([[[0.0, 0.0, 0.0], [0.8, 0.0, 0.0]],
                     [[0.2, 0.0, 0.0], [0.9, 0.0, 0.0]]])  # [W, P, 3]


def _records(every=2, T=10, dt=0.1, down_at=None):
    """Two episodes of ``T`` steps under :data:`COMMANDS` (a change at 0.5 s): the model
    predicts every sequence on the command, the simulator 0.1 m/s faster; the family's
    objective 0.3 below the policy's on the model, 0.1 on the simulator; the robot 0.05 m/s
    faster than asked."""
    W, S = COMMANDS.shape[0], 4
    piece = (np.arange(T) * dt >= 0.5 - 1e-9).astype(int)
    cmd = COMMANDS[:, piece]  # [W, T, 3]
    track = np.zeros((W, T, S, 2, 3))
    track[..., 0, :] = cmd[:, :, None]
    track[..., 1, :] = cmd[:, :, None] + np.array([0.1, 0.0, 0.0])
    cost = np.zeros((W, T, S, 2))
    cost[:, :, 3] = [-0.3, -0.1]  # the family's
    value = np.zeros((W, T, S, 2))
    value[:, :, 3] = [0.2, 0.05]  # the family's end value: most of its lower cost on the model
    recorded = np.zeros((W, T), bool)
    recorded[:, ::every] = True
    down = np.zeros((W, T), bool)
    if down_at is not None:
        down[down_at] = True
    share = np.tile([0.2, 0.3, 0.5], (W, T, 1))
    swap = np.zeros((W, T, 5, 2))  # the base velocity carries a quarter, all of it the whole
    swap[:, :, 0] = [-0.05, -0.01]
    swap[:, :, 4] = [-0.2, -0.05]
    return dict(track=track, cost=cost, value=value, swap=swap, share=share, command=cmd,
                now=cmd + np.array([0.05, 0.0, 0.0]), down=down, recorded=recorded)


def test_replays_are_grouped_by_command_after_the_settling_time(experiment):
    mod = experiment("plan_bias")
    groups = {g["label"]: g for g in mod.summarise(_records(), COMMANDS, BOUNDS, [0.0, 0.5],
                                                  0.2, 0.1)}
    stops, fast, slow = (groups["stops (all zero)"], groups["forward 0.5 or more"],
                         groups["forward under 0.5"])
    # recorded every other step; settled 0.2 s into each command: 0.2 and 0.4 s of the first
    # piece (world 0's stop, world 1's slow command), 0.8 s of the second (both fast)
    assert (stops["steps"], stops["episodes"]) == (2, 1)
    assert (slow["steps"], slow["episodes"]) == (2, 1)
    assert (fast["steps"], fast["episodes"]) == (2, 2)
    for g in (stops, fast, slow):
        for seq in mod.SEQUENCES:
            f = g["forward"][seq]
            assert f["model"]["mean"] == pytest.approx(0.0, abs=1e-9)
            assert f["true"]["mean"] == pytest.approx(0.1)
            assert f["bias"]["mean"] == pytest.approx(-0.1)
        assert g["executed_forward"]["mean"] == pytest.approx(0.05)
        assert g["share"]["family"]["mean"] == pytest.approx(0.5)
        c = g["cost_family_minus_policy"]
        assert (c["model"]["mean"], c["true"]["mean"]) == (pytest.approx(-0.3),
                                                            pytest.approx(-0.1))
        v = g["value_part"]
        assert (v["model"]["mean"], v["true"]["mean"]) == (pytest.approx(-0.2),
                                                            pytest.approx(-0.05))
        w = g["value_swap"]
        assert (w["base velocity"]["model"]["mean"], w["all"]["true"]["mean"]) == (
            pytest.approx(-0.05), pytest.approx(-0.05))
        assert w["orientation"]["model"]["mean"] == pytest.approx(0.0, abs=1e-12)
    assert groups["lateral 0.15 or more (either sign)"]["episodes"] == 0
    # a step the robot was down at does not count
    fewer = {g["label"]: g for g in mod.summarise(_records(down_at=(1, 8)), COMMANDS, BOUNDS,
                                                 [0.0, 0.5], 0.2, 0.1)}
    assert (fewer["forward 0.5 or more"]["steps"], fewer["forward 0.5 or more"]["episodes"]) \
        == (1, 1)
    # a planner without the family: its rows are NaN, read as none (no warning, no zero)
    rec = _records()
    rec["track"][:, :, 3] = np.nan
    rec["cost"][:, :, 3] = np.nan
    rec["value"][:, :, 3] = np.nan
    import warnings
    with warnings.catch_warnings():
        warnings.filterwarnings("error", message="Mean of empty slice")
        bare = mod.summarise(rec, COMMANDS, BOUNDS, [0.0, 0.5], 0.2, 0.1)
    fast = next(g for g in bare if g["label"] == "forward 0.5 or more")
    assert fast["forward"]["family"]["model"] is None
    assert fast["cost_family_minus_policy"]["model"] is None
    assert fast["forward"]["policy"]["true"]["mean"] == pytest.approx(0.1)
    assert "| n/a, n/a |" in mod.markdown(dict(command="c", code="abc", candidate="r", every=2,
                                                 config=dict(worlds=2, seconds=1.0, seed=0,
                                                             model="m"), groups=bare))
    table = dict(command="c", code="abc", candidate="r.msgpack", every=2,
                 config=dict(worlds=2, seconds=1.0, seed=0, model="stride=RUN"),
                 groups=list(groups.values()))
    md = mod.markdown(table)
    assert "| forward 0.5 or more | 2 (2) | +0.050 | +0.000, +0.100 |" in md
    assert "| lateral 0.15 or more (either sign) | 0 |" in md
    assert "| -0.300, -0.100 | -0.200, -0.050 |" in md
    assert ("| forward 0.5 or more | -0.200, -0.050 | -0.050, -0.010 | +0.000, +0.000 | "
            "+0.000, +0.000 | +0.000, +0.000 | -0.200, -0.050 |") in md
    assert "tracked minus asked" not in md  # no integral: no column
    # a velocity integral moved the planner's command 0.1 m/s below the asked one: the
    # sequences read against the command it tracked, the executed speed against the asked one
    rec = _records()  # the robot still 0.05 m/s faster than asked
    rec["command"] = rec["command"] - np.array([0.1, 0.0, 0.0])
    rec["track"][..., 0] -= 0.1  # every sequence as before, about the planner's command
    moved = {g["label"]: g for g in mod.summarise(rec, COMMANDS, BOUNDS, [0.0, 0.5], 0.2, 0.1)}
    fast = moved["forward 0.5 or more"]
    assert fast["executed_forward"]["mean"] == pytest.approx(0.05)
    assert fast["tracked_minus_asked"]["mean"] == pytest.approx(-0.1)
    assert fast["forward"]["plan"]["model"]["mean"] == pytest.approx(0.0, abs=1e-9)
    assert fast["forward"]["plan"]["true"]["mean"] == pytest.approx(0.1)
    md = mod.markdown({**table, "groups": list(moved.values())})
    assert "| executed | tracked minus asked |" in md and "|---|---:|---:|---:|" in md
    lines = md.splitlines()
    head = next(i for i, x in enumerate(lines) if x.startswith("| commands |"))
    assert lines[head - 1] == "" and "moved by its velocity integral" in lines[head - 2]
    assert "| forward 0.5 or more | 2 (2) | +0.050 | -0.100 | +0.000, +0.100 |" in md
    assert "| lateral 0.15 or more (either sign) | 0 | | | | | | | | | |" in md


def test_bad_settings_are_named_before_any_work(experiment):
    mod = experiment("plan_bias")
    from stride_jax.jobs.select_learned import SelectConfig
    with pytest.raises(ValueError, match="every=0"):
        mod.run(SelectConfig(candidates="a=x.msgpack"), 0, "c")
    with pytest.raises(ValueError, match="candidates"):
        mod.run(SelectConfig(), 5, "c")
    with pytest.raises(ValueError, match="got 2"):
        mod.run(SelectConfig(candidates="a=x.msgpack,b=y.msgpack"), 5, "c")
    with pytest.raises(FileNotFoundError, match="no learned reward/value file"):
        mod.run(SelectConfig(candidates="a=/nonexistent.msgpack"), 5, "c")
    with pytest.raises(ValueError, match="sensor noise"):
        mod.run(SelectConfig(candidates="a=x.msgpack", sensor_noise=1.0), 5, "c")


@pytest.mark.slow  # ~2 min of MJX compiles; its parts run in make test (above; test_mppi's along)
def test_a_planner_through_the_simulator_predicts_its_plans_exactly(tmp_path, experiment):
    """End to end on Go1's tiny validation episodes: a planner whose model is the simulator
    itself (the oracle, no disturbance estimate) predicts every replayed sequence as the
    simulator runs it (no model bias, no objective gap), and its groups' weights sum to one."""
    mod = experiment("plan_bias")
    out = tmp_path / "bias"
    table = mod.main(["--preset", "tiny", "--policy", "results/policies/ppo_go1",
                      "--model", "oracle", "--worlds", "2", "--seconds", "0.2",
                      "--change-s", "0.1", "--settle-s", "0.0", "--mppi.family-samples", "2",
                      "--candidates", "a=results/learned_go1/reward_value.msgpack",
                      "--every", "2", "--out", str(out)])
    moving = [g for g in table["groups"] if g["episodes"]]
    assert moving
    for g in moving:
        for seq in mod.SEQUENCES:
            assert g["forward"][seq]["bias"]["mean"] == pytest.approx(0.0, abs=1e-5)
        c = g["cost_family_minus_policy"]
        assert c["model"]["mean"] == pytest.approx(c["true"]["mean"], abs=1e-4)
        assert sum(g["share"][k]["mean"] for k in mod.GROUPS) == pytest.approx(1.0, abs=1e-5)
        # the policy's whole state in the family's end state: the policy's end value
        for side in ("model", "true"):
            assert g["value_swap"]["all"][side]["mean"] == pytest.approx(
                g["value_part"][side]["mean"], abs=1e-4)
    assert (out / "bias.md").is_file() and (out / "bias.png").is_file()
