"""experiments/trust_gate.py: where the model-trust gate handed the robot to the policy, from a
closed loop's rows and traces."""

import json

import numpy as np
import pytest

from stride_jax.control import mppi


def test_trigger_runs_count_the_estimates_past_the_limit_and_the_handovers(tmp_path, experiment):
    mod = experiment("trust_gate")
    assert mod.longest_run([0, 1, 1, 0, 1, 1, 1, 0]) == 3 and mod.longest_run([]) == 0
    assert mod.longest_run([1, 1]) == 2 and mod.longest_run([0, 0]) == 0
    dist = np.zeros((10, 6), np.float32)
    dist[[1, 2, 5, 6, 7], 0] = 3.0  # two runs past 2.5: of 2 and of 3 periods
    dist[3, 3:] = 9.0  # the angular entries do not count
    status = np.full(10, mppi.PLANNED, np.int32)
    status[6:9] = mppi.DISTRUSTED
    t = 0.02 * np.arange(1, 11, dtype=np.float32)
    fallen = np.zeros(10, bool)
    fallen[8:] = True
    np.savez(tmp_path / "trace_push_stride.npz", disturbance=dist, status=status, t=t,
             fallen=fallen)
    got = mod.trigger_runs(tmp_path / "trace_push_stride.npz", 2.5, window_s=0.1)
    # before the first handover (period 6) the five-period windows hold at most 3 past the limit
    assert got == dict(over=5, longest=3, most_in_window=3, handed=3, periods=10,
                       first_over_s=pytest.approx(0.04), handed_at_s=pytest.approx(0.14),
                       fell_at_s=pytest.approx(0.18))
    assert mod.trigger_runs(tmp_path / "trace_push_stride.npz", 2.5, window_s=1.0)[
        "most_in_window"] == 3  # periods 1, 2 and 5
    status[:] = mppi.PLANNED  # never handed over: the whole trace's windows
    np.savez(tmp_path / "trace_push_stride.npz", disturbance=dist, status=status, t=t,
             fallen=np.zeros(10, bool))
    got = mod.trigger_runs(tmp_path / "trace_push_stride.npz", 2.5, window_s=1.0)
    assert (got["most_in_window"], got["handed_at_s"], got["fell_at_s"]) == (5, None, None)
    assert mod.trigger_runs(tmp_path / "trace_push_stride.npz", 2.5, window_s=0.1)[
        "most_in_window"] == 3  # five periods hold at most three of them
    with pytest.raises(ValueError, match="positive"):
        mod.trigger_runs(tmp_path / "trace_push_stride.npz", 2.5, window_s=0.0)
    # the downward entry alone (a down-reading gate): the x entries past 2.5 do not count
    dist[[4, 5], 2] = -3.0
    np.savez(tmp_path / "trace_push_stride.npz", disturbance=dist, status=status, t=t,
             fallen=np.zeros(10, bool))
    got = mod.trigger_runs(tmp_path / "trace_push_stride.npz", 2.5, component="down")
    assert (got["over"], got["longest"], got["first_over_s"]) == (2, 2, pytest.approx(0.10))
    assert mod.trigger_runs(tmp_path / "trace_push_stride.npz", 2.5)["over"] == 6  # the norm
    with pytest.raises(ValueError, match="component 'up'"):
        mod.trigger_runs(tmp_path / "trace_push_stride.npz", 2.5, component="up")
    np.savez(tmp_path / "trace_push_policy.npz", v_base=np.zeros((10, 3)))
    with pytest.raises(ValueError, match="no disturbance estimate"):
        mod.trigger_runs(tmp_path / "trace_push_policy.npz", 2.5)


def test_row_shares_read_the_headline_rows_of_the_named_models(tmp_path, experiment, capsys):
    mod = experiment("trust_gate")
    row = lambda model, part, share, v=0.1: dict(scenario="push", model=model, part=part,
                                                 seed=2, vel_rmse=v, fell=False,
                                                 distrust_share=share)
    table = {"parts": {"a": {}, "old": {}}, "headline": {"parts": ["a"]},
             "rows": [row("stride@a", "a", 0.5), row("stride_s1@a", "a", 0.3),
                      row("onn@a", "a", 0.9), row("stride@old", "old", 1.0)]}
    got = mod.row_shares(table, ["stride", "stride_s1"])
    assert [r[0] for r in got["push"]["rows"]] == ["stride@a", "stride_s1@a"]
    assert got["push"]["mean_share"] == pytest.approx(0.4)
    p = tmp_path / "closed_loop.json"
    p.write_text(json.dumps(table))
    assert mod.main(["rows", str(p), "--models", "stride"]) == 0
    assert "| push | stride@a (2) 0.100, 50% | 50% |" in capsys.readouterr().out
    with pytest.raises(SystemExit, match="no row of delan"):
        mod.main(["rows", str(p), "--models", "delan"])
    with pytest.raises(SystemExit, match="no trace"):
        mod.main(["traces", str(tmp_path), "--limit", "2.5"])


def test_overspeed_says_who_acted_when_the_robot_ran_past_its_command(tmp_path, experiment, capsys):
    """A trace whose upright forward speed passed the command by more than ``over``: when it
    first did, by how much at most, the handed-over share of the window before it and of the
    rest of the episode, and the fall; None where it never did; a fallen robot's speed and a
    trace without a planner's status are not read."""
    mod = experiment("trust_gate")
    n = 10
    t = 0.1 * np.arange(1, n + 1, dtype=np.float32)
    v = np.zeros((n, 3), np.float32)
    v[:, 0] = [1.0, 1.0, 1.1, 1.2, 1.4, 1.5, 1.3, 1.0, 3.0, 3.0]  # 3.0: fallen, not read
    command = np.zeros((n, 3), np.float32)
    command[:, 0] = 1.0
    status = np.full(n, mppi.PLANNED, np.int32)
    status[[1, 2, 3, 4, 5]] = mppi.DISTRUSTED
    fallen = np.zeros(n, bool)
    fallen[8:] = True
    np.savez(tmp_path / "trace_tilt15_stride.npz", t=t, v_base=v, command=command,
             status=status, fallen=fallen)
    got = mod.overspeed(tmp_path / "trace_tilt15_stride.npz", 0.25, window_s=0.3)
    # first past 0.25 over at period 4 (1.4); the three periods before: 1, 2, 3 all handed over
    assert got == dict(first_s=pytest.approx(0.5), most=pytest.approx(0.5),
                       handed_before=pytest.approx(1.0), handed_after=pytest.approx(2 / 6),
                       fell_at_s=pytest.approx(0.9))
    assert mod.overspeed(tmp_path / "trace_tilt15_stride.npz", 0.6) is None
    assert mod.main(["overspeed", str(tmp_path), "--over", "0.25", "--scenario", "tilt15"]) == 0
    out = capsys.readouterr().out
    assert "1 of 1 traces ran more than 0.25 m/s" in out and "| 0.50 | 0.50 |" in out
    with pytest.raises(SystemExit, match="no trace_push_"):
        mod.main(["overspeed", str(tmp_path), "--over", "0.25", "--scenario", "push"])
    np.savez(tmp_path / "trace_tilt15_policy.npz", t=t, v_base=v, command=command, fallen=fallen)
    with pytest.raises(ValueError, match="no status"):
        mod.overspeed(tmp_path / "trace_tilt15_policy.npz", 0.25)
    with pytest.raises(ValueError, match="positive"):
        mod.overspeed(tmp_path / "trace_tilt15_stride.npz", 0.25, window_s=0)
