"""experiments/tracking_error.py: a planner's velocity error split into a steady offset and the
variance about it, from saved closed-loop traces."""

import json

import numpy as np
import pytest

from stride_jax.control.episode import piece_errors, tracked


def _trace(folder, model, offset, sway, scenario="changes", draw=0, n=200, dt=0.02,
           change_at=100, fall_at=None, offset_after=None):
    """A closed-loop row and its trace, as the closed loop writes them: velocity = command +
    ``offset`` + a lateral sine of amplitude ``sway``, the command stepping once at
    ``change_at``; ``draw`` is the planner's draw (the row's ``seed``, ``episode``)."""
    from stride_jax.jobs.closed_loop import trace_name
    t = dt * np.arange(n, dtype=np.float32)
    command = np.zeros((n, 3), np.float32)
    command[:, 0] = 0.5
    command[change_at:, 0] = 0.8
    v = command.copy()
    v[:, :2] += offset
    if offset_after is not None:  # another offset after the change
        v[change_at:, :2] += np.asarray(offset_after) - offset
    v[:, 1] += sway * np.sin(2 * np.pi * 2.0 * t)
    fallen = np.zeros(n, bool)
    if fall_at is not None:
        fallen[fall_at:] = True
    np.savez(folder / trace_name(scenario, model, draw, draw), t=t, command=command, v_base=v,
             fallen=fallen)
    table = folder / "closed_loop.json"
    rows = json.loads(table.read_text())["rows"] if table.is_file() else []
    rows.append(dict(scenario=scenario, model=model, seed=draw, episode=draw,
                     fell=fall_at is not None, vel_rmse=0.0, ms_per_step=1.0))
    table.write_text(json.dumps(dict(env={}, rows=rows)))


def test_scored_steps_follow_the_settle_time_and_the_fall():
    import types
    t = 0.02 * np.arange(10)
    command = np.zeros((10, 3))
    command[4:, 0] = 1.0
    fallen = np.zeros(10, bool)
    fallen[8:] = True
    use = tracked(types.SimpleNamespace(t=t, command=command, fallen=fallen), settle_s=0.03)
    assert use.tolist() == [False, False, True, True, False, False, True, True, False, False]


def test_each_command_piece_gets_its_own_error():
    """piece_errors splits the scored steps by the schedule's pieces: an error that arises only
    under the second command is that piece's alone; a piece with no scored step is NaN."""
    import types
    t = 0.02 * np.arange(12)
    command = np.zeros((12, 3))
    command[4:8] = [1.0, 0.0, 0.5]  # pieces start at 0, 0.08 and 0.16 s
    command[8:] = [0.2, 0.0, 0.0]
    v, w = np.zeros((12, 3)), np.zeros((12, 3))
    v[:, 0] = command[:, 0]
    v[4:8, 0] += 0.3  # the second piece misses by 0.3 m/s ...
    w[4:8, 2] = 0.5 - 0.1  # ... and 0.1 rad/s
    fallen = np.zeros(12, bool)
    fallen[10:] = True  # the third piece scores two steps before the fall
    tr = types.SimpleNamespace(t=t, command=command, v_base=v, w_base=w, fallen=fallen)
    e = piece_errors(tr, [0.0, 0.08, 0.16], settle_s=0.0)
    np.testing.assert_allclose(e["vel"], [0.0, 0.3, 0.0], atol=1e-12)
    np.testing.assert_allclose(e["yaw"], [0.0, 0.1, 0.0], atol=1e-12)
    np.testing.assert_allclose(e["offset"], [[0, 0, 0], [0.3, 0, -0.1], [0, 0, 0]], atol=1e-12)
    vel = piece_errors(tr, [0.0, 0.08, 0.16, 0.2], settle_s=0.0)["vel"]  # the last: all fallen
    assert np.isnan(vel[-1]) and np.isfinite(vel[:3]).all()


def test_offsets_and_variance_add_up_to_the_mean_square_error(tmp_path, experiment):
    mod = experiment("tracking_error")
    for name, off in (("stride", -0.01), ("stride_s1", -0.03), ("delan", 0.0)):
        _trace(tmp_path, name, np.array([off, 0.0]), sway=0.04)
    _trace(tmp_path, "stride", np.array([-0.01, 0.0]), sway=0.04, draw=1)
    _trace(tmp_path, "stride_shared", np.array([1.0, 0.0]), sway=0.0)  # not stride's
    _trace(tmp_path, "stride", np.array([1.0, 0.0]), sway=0.0, scenario="push")  # another scenario
    r = mod.decompose(tmp_path, "changes", "stride")
    assert r["seeds"] == [0, 1] and r["episodes"] == 3
    # seed 0 twice (two draws) at -0.01, seed 1 at -0.03, equal steps each: (-0.01 - 0.01 - 0.03) / 3
    assert r["offset_x"] == pytest.approx(-0.05 / 3, abs=1e-6)
    assert r["seed_offset_x"] == pytest.approx([-0.01, -0.03], abs=1e-6)
    assert r["offset_y"] == pytest.approx(0.0, abs=2e-3)
    assert r["var_y"] == pytest.approx(0.04 ** 2 / 2, rel=0.1)  # a sine's variance
    assert r["mse"] == pytest.approx(r["offset_x"] ** 2 + r["offset_y"] ** 2 + r["var_x"]
                                     + r["var_y"], rel=1e-5)
    # the steps within 0.5 s of a change are not scored: 200 - 25 - 25 per trace
    assert r["steps"] == 3 * 150
    # the settle time is the run's own (its config), unless given
    table = tmp_path / "closed_loop.json"
    table.write_text(json.dumps(dict(json.loads(table.read_text()),
                                     env={"config": {"settle_s": 1.0}})))
    assert mod.decompose(tmp_path, "changes", "stride")["steps"] == 3 * 100
    assert mod.decompose(tmp_path, "changes", "stride", settle_s=0.5)["steps"] == 3 * 150


def test_the_script_writes_table_json_and_figure_and_names_bad_picks(tmp_path, experiment):
    mod = experiment("tracking_error")
    _trace(tmp_path, "stride", np.array([-0.01, 0.0]), sway=0.04)
    _trace(tmp_path, "delan", np.array([0.0, 0.0]), sway=0.04, fall_at=60)
    out = tmp_path / "out" / "err"
    assert mod.main(["--scenario", "changes", f"STRIDE={tmp_path}:stride",
                     f"DeLaN={tmp_path}:delan", "--out", str(out)]) == 0
    saved = json.loads(out.with_suffix(".json").read_text())
    rows = saved["rows"]
    assert saved["command"].startswith("python experiments/tracking_error.py --scenario changes")
    assert rows["DeLaN"]["steps"] == 60 - 25  # up to the fall
    assert "| STRIDE | 1 | 150 |" in out.with_suffix(".md").read_text()
    assert out.with_suffix(".png").stat().st_size > 1000
    md = out.with_suffix(".md").read_text()
    assert "| 0-2 s (0.5, 0, 0) | 2-4 s (0.8, 0, 0) | whole |" in md  # per segment
    assert "| DeLaN | 1 (1 fell) | " in md
    with pytest.raises(SystemExit, match="no row of onn in 'changes'"):
        mod.main(["--scenario", "changes", f"ONN={tmp_path}:onn", "--out", str(out)])
    with pytest.raises(SystemExit, match="expected LABEL=FOLDER:MODEL"):
        mod.main(["--scenario", "changes", str(tmp_path), "--out", str(out)])
    (tmp_path / "trace_changes_stride.npz").unlink()
    with pytest.raises(SystemExit, match="trace_changes_stride.npz: no trace of the row stride"):
        mod.main(["--scenario", "changes", f"STRIDE={tmp_path}:stride", "--out", str(out)])


def test_each_command_segment_scores_its_own_error(tmp_path, experiment):
    """Per stretch of constant command: each trace's RMSE over its scored steps there, the mean
    over the traces; a fall leaves the steps after it unscored; traces of another schedule are
    an error."""
    mod = experiment("tracking_error")
    _trace(tmp_path, "stride", np.array([0.1, 0.0]), sway=0.0, offset_after=[0.4, 0.0])
    _trace(tmp_path, "stride_s1", np.array([0.3, 0.0]), sway=0.0, offset_after=[0.0, 0.0])
    g = mod.decompose(tmp_path, "changes", "stride")["segments"]
    assert np.allclose([s["command"] for s in g["schedule"]], [[0.5, 0.0, 0.0], [0.8, 0.0, 0.0]])
    assert [s["start"] for s in g["schedule"]] == pytest.approx([0.0, 2.0])
    assert g["rmse"] == pytest.approx([0.2, 0.2], abs=1e-6)
    assert g["whole"] == pytest.approx((np.sqrt((0.01 + 0.16) / 2) + np.sqrt(0.09 / 2)) / 2, abs=1e-6)
    assert g["fell"] == 0
    _trace(tmp_path, "delan", np.array([0.1, 0.0]), sway=0.0, fall_at=80)
    g = mod.decompose(tmp_path, "changes", "delan")["segments"]
    assert g["rmse"][0] == pytest.approx(0.1, abs=1e-6) and np.isnan(g["rmse"][1]) and g["fell"] == 1
    _trace(tmp_path, "stride", np.array([0.1, 0.0]), sway=0.0, draw=1, change_at=120)
    with pytest.raises(ValueError, match="schedule differs"):
        mod.decompose(tmp_path, "changes", "stride")


def test_windows_place_a_transient_offset_in_time(tmp_path, experiment):
    """``--window-s``: an offset that only the first half carries shows in the first windows'
    forward offset and RMSE, not in the later ones."""
    mod = experiment("tracking_error")
    _trace(tmp_path, "stride", np.array([0.05, 0.0]), sway=0.0, change_at=200, offset_after=None)
    path = next(tmp_path.glob("trace_*.npz"))
    with np.load(path) as z:
        d = {k: z[k] for k in z.files}
    d["v_base"][101:, 0] -= 0.05  # the offset gone after 2 s (a step's time ends its period)
    np.savez(path, **d)
    w = mod.decompose(tmp_path, "changes", "stride", settle_s=0.0, window_s=1.0)["windows"]
    assert w["start"] == [0.0, 1.0, 2.0, 3.0]
    np.testing.assert_allclose(w["offset_x"], [0.05, 0.05, 0.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(w["rmse"], [0.05, 0.05, 0.0, 0.0], atol=1e-6)
    with pytest.raises(ValueError, match="positive"):
        mod.by_window([mod.load(path)], 0.0, 0.0)


def test_each_trace_is_read_once(tmp_path, experiment, monkeypatch):
    """The split, the stretches, the windows and who acted all read one load of each trace."""
    mod = experiment("tracking_error")
    for seed in range(3):
        _trace(tmp_path, "stride", np.array([0.05, 0.0]), sway=0.0, change_at=200,
               offset_after=None, draw=seed)
    read, load = [], mod.load
    monkeypatch.setattr(mod, "load", lambda path, planner=True: read.append(path) or load(path, planner))
    r = mod.decompose(tmp_path, "changes", "stride", settle_s=0.0, window_s=1.0)
    assert r["episodes"] == 3 and len(read) == 3 and len(set(read)) == 3


def test_who_acted_splits_the_error_by_the_trust_gate(tmp_path, experiment):
    """Where a trace records the planner's status, the pooled error splits over the steps the
    trust gate handed to the policy and those the plan acted on, and each window says how many
    it handed over; the policy alone (its status all zeros, as the closed loop records it) has
    no split."""
    from stride_jax.control import mppi
    mod = experiment("tracking_error")
    _trace(tmp_path, "stride", np.array([0.0, 0.0]), sway=0.0, change_at=200)
    _trace(tmp_path, "policy", np.array([0.02, 0.0]), sway=0.0, change_at=200)
    ppath = next(tmp_path.glob("trace_changes_policy*.npz"))
    with np.load(ppath) as z:
        pd = {k: z[k] for k in z.files}
    np.savez(ppath, status=np.zeros(200, np.int32), **pd)  # the policy alone records zeros
    path = next(tmp_path.glob("trace_changes_stride*.npz"))
    with np.load(path) as z:
        d = {k: z[k] for k in z.files}
    status = np.full(200, mppi.PLANNED, np.int32)
    status[101:151] = mppi.DISTRUSTED  # (2, 3] s handed over (a step's time ends its period),
    d["v_base"][101:151, 0] += 0.1  # with an offset of 0.1 there
    np.savez(path, status=status, **d)
    r = mod.decompose(tmp_path, "changes", "stride", settle_s=0.0, window_s=1.0)
    assert r["gate"]["share"] == pytest.approx(0.25)
    assert r["gate"]["rmse_handed_over"] == pytest.approx(0.1, abs=1e-6)
    assert r["gate"]["rmse_planned"] == pytest.approx(0.0, abs=1e-6)
    np.testing.assert_allclose(r["windows"]["handed_over"], [0.0, 0.0, 1.0, 0.0], atol=1e-6)
    p = mod.decompose(tmp_path, "changes", "policy", settle_s=0.0, window_s=1.0)
    assert p["gate"] is None and np.isnan(p["windows"]["handed_over"]).all()
    assert mod.main([f"S={tmp_path}:stride", f"P={tmp_path}:policy", "--scenario", "changes",
                     "--window-s", "1", "--settle-s", "0", "--out", str(tmp_path / "out")]) == 0
    md = (tmp_path / "out.md").read_text()
    assert "| S | 25% | 0.100 | 0.000 |" in md and "| P | - | - | - |" in md
    assert "| S | handed to the policy | 0% | 0% | 100% | 0% |" in md
    assert "| P | handed to the policy |" not in md
