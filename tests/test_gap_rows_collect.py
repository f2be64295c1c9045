"""experiments/gap_rows_collect.py: rows run one by one gathered into the benchmark's row folder,
a later folder's row replacing an earlier one's, each with the code it ran at."""

import json

import pytest

from stride_jax.jobs import gap_bench as bench
from stride_jax.jobs import gap_bench_independent as bi


def _row(folder, case, noisy, verdict, code=None):
    folder.mkdir(parents=True, exist_ok=True)
    data = {"row": {"case": case, "noisy": noisy, "verdict": verdict}} | ({"code": code} if code else {})
    (folder / f"{case:02d}-{'noisy' if noisy else 'clean'}.json").write_text(json.dumps(data))


def test_rows_are_gathered_in_order_with_their_code(experiment, tmp_path):
    mod = experiment("gap_rows_collect")
    a, b, out = tmp_path / "a", tmp_path / "b", tmp_path / "out"
    _row(a, 1, False, "first")
    _row(a, 2, True, "kept")
    _row(b, 1, False, "second", code="fromfile")
    res = mod.collect([f"{a}=abc1234", str(b)], str(out), "default", log=lambda s: None)
    assert res["complete"] is False and res["done"] == 2 and res["total"] == len(bi.cases(bi.PRESETS["default"])) * 2
    rows = bench.load_rows(bench.rows_dir(bi.PRESETS["default"], out), bi.PRESETS["default"])
    assert rows[(1, False)] == {"row": {"case": 1, "noisy": False, "verdict": "second"}, "code": "fromfile"}
    assert rows[(2, True)]["code"] == "abc1234" and rows[(2, True)]["row"]["verdict"] == "kept"
    _row(tmp_path / "c", 3, False, "no code")
    with pytest.raises(SystemExit, match="records no code"):
        mod.collect([str(tmp_path / "c")], str(out), "default", log=lambda s: None)
    with pytest.raises(SystemExit, match="no rows"):
        mod.collect([str(tmp_path / "empty")], str(out), "default", log=lambda s: None)
