"""experiments/gap_bench_compare.py: two runs of a gap benchmark set side by side, row by row."""

import json

import pytest


def _write(folder, name, verdict, named, confident, correct, code, best=None, seconds=100.0):
    folder.mkdir(parents=True, exist_ok=True)
    row = dict(planted={"damping": [1.5]}, verdict=verdict, named=named, confident=confident,
               correct=correct, seconds=seconds, best={"params": best or {}})
    (folder / f"{name}.json").write_text(json.dumps(dict(config={}, code=code, row=row)))


def test_rows_that_moved_are_the_ones_whose_call_changed(experiment, tmp_path):
    mod = experiment("gap_bench_compare")
    a, b = tmp_path / "a", tmp_path / "b"
    _write(a, "01-clean", "explained", ["damping"], True, True, "old", {"damping": [1.46]})
    _write(b, "01-clean", "explained", ["damping"], True, True, "new", {"damping": [1.45]})  # value only
    _write(a, "01-noisy", "explained", ["damping"], True, True, "old")
    _write(b, "01-noisy", "unexplained by the library", [], False, False, "new")
    _write(a, "02-clean", "explained", ["delay"], True, True, "old")  # not rerun: not compared
    res = mod.compare(a, b)
    assert res["compared"] == 2 and res["moved"] == 1
    assert [r["moved"] for r in res["rows"]] == [False, True]
    assert (res["right_before"], res["right_after"]) == (2, 1)
    assert mod.main([str(a), str(b), "--out", str(tmp_path / "cmp")]) == 0
    md = (tmp_path / "cmp.md").read_text()
    assert "2 rows compared, **1 moved**" in md and "| 01-noisy |" in md and "code new" in md
    assert json.loads((tmp_path / "cmp.json").read_text())["command"].startswith(
        "python experiments/gap_bench_compare.py")


def test_missing_rows_and_folders_are_clear_errors(experiment, tmp_path):
    mod = experiment("gap_bench_compare")
    a, b = tmp_path / "a", tmp_path / "b"
    _write(b, "03-clean", "explained", ["armature"], True, True, "new")
    with pytest.raises(SystemExit, match="no such folder"):
        mod.compare(a, b)
    a.mkdir()
    with pytest.raises(SystemExit, match="no row for 03-clean.json"):
        mod.compare(a, b)
    with pytest.raises(SystemExit, match="no rows"):
        mod.compare(b, tmp_path / "a")
