"""The blind benchmark runs in a process pool with the same rows as serially, resumes from the rows on
disk, and refuses rows written with another config."""

import dataclasses
import json

import pytest

from stride_jax.jobs import gap as cli, gap_bench as bench

# 2 cases (control, damping) x clean/noisy = 4 rows of a few seconds each on the pendulum
CFG = bench.BenchConfig(robot="pendulum", trajectories=4, steps=60, magnitudes={"damping": (0.5,)}, pairs=(),
                        out_of_library=(), diagnose="tiny", name="t")
TIMING = ("seconds", "row_seconds")


def _rows(result: dict) -> list[dict]:
    return [{k: v for k, v in r.items() if k not in TIMING} for r in result["cases"]]


def test_a_rerun_skips_rows_on_disk(tmp_path):
    serial = bench.run(CFG, tmp_path / "serial", log=lambda s: None)
    assert serial["complete"]
    assert len(serial["cases"]) == 4 and [(r["case"], r["noisy"]) for r in serial["cases"]] == [
        (0, False), (0, True), (1, False), (1, True)]
    assert serial["cases"][2]["named"] == ["damping"]
    # an interrupted run: one row lost, one on disk (marked, to see that it is not recomputed)
    folder = bench.rows_dir(CFG, tmp_path / "serial")
    bench.row_path(folder, 1, True).unlink()
    kept = bench.row_path(folder, 0, True)
    rec = json.loads(kept.read_text())
    rec["row"]["seconds"] = -1.0
    kept.write_text(json.dumps(rec))
    lines = []
    again = bench.run(CFG, tmp_path / "serial", log=lines.append)
    assert "3 of 4 rows already" in lines[0]
    assert again["cases"][1]["seconds"] == -1.0  # skipped
    assert _rows(again) == _rows(serial)  # the lost row recomputed as before
    assert (tmp_path / "serial" / "t.md").is_file()


@pytest.mark.slow  # the rows themselves: test_a_rerun_skips_rows_on_disk (serial)
def test_pool_gives_the_serial_rows(tmp_path):
    serial = bench.run(CFG, tmp_path / "serial", log=lambda s: None)
    pooled = bench.run(CFG, tmp_path / "pool", log=lambda s: None, workers=2)
    assert serial["complete"] and pooled["complete"]
    assert _rows(pooled) == _rows(serial)


def test_minutes_zero_starts_nothing_and_writes_no_summary(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(bench.PRESETS, "test", CFG)
    assert cli.main(["bench", "--preset", "test", "--out", str(tmp_path), "--workers", "2", "--minutes", "0"]) == 0
    out = capsys.readouterr().out
    assert "0 of 4 rows done" in out and "rerun the same command to continue" in out
    assert not (tmp_path / "t.md").exists() and not (tmp_path / "t.json").exists()


def test_rows_from_another_config_are_refused(tmp_path, capsys, monkeypatch):
    row = {"case": 0, "noisy": False, "kind": "control", "verdict": "no significant gap"}
    bench.save_row(bench.rows_dir(CFG, tmp_path), CFG, row, "test")
    assert set(bench.load_rows(bench.rows_dir(CFG, tmp_path), CFG)) == {(0, False)}
    monkeypatch.setitem(bench.PRESETS, "test", dataclasses.replace(CFG, steps=80))
    assert cli.main(["bench", "--preset", "test", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "another benchmark config (steps: 60 there, 80 now)" in err and "fresh --out folder" in err
    with pytest.raises(bench.BenchError, match="workers and threads must be at least 1"):
        bench.run(CFG, tmp_path, workers=0)


def test_a_row_written_before_a_setting_existed_counts_as_that_settings_default(tmp_path):
    """A benchmark setting added later (its default reproducing what ran before) does not orphan
    the rows already on disk: a row whose stored config lacks it loads under the default and is
    refused under any other value, named."""
    from stride_jax.jobs import gap_bench_independent as bi
    cfg = bi.PRESETS["tiny"]
    folder = bench.rows_dir(cfg, tmp_path)
    row = {"case": 0, "noisy": False, "kind": "control", "verdict": "no significant gap"}
    path = bench.row_path(folder, 0, False)
    bench.save_row(folder, cfg, row, "test")
    rec = json.loads(path.read_text())
    del rec["config"]["sensor_spec"]  # as written before session 44
    path.write_text(json.dumps(rec))
    assert set(bench.load_rows(folder, cfg)) == {(0, False)}
    with pytest.raises(bench.BenchError, match="sensor_spec: False there, True now"):
        bench.load_rows(folder, dataclasses.replace(cfg, sensor_spec=True))
