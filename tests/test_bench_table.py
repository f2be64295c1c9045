"""The benchmarks' one table writer: a JSON file of rows and environment, a Markdown table."""

import json

import pytest

from stride_jax.jobs import bench_table


def test_writes_json_and_markdown_tagged_by_backend(tmp_path):
    rows = [dict(robot="go1", ms=1.5), dict(robot="g1", ms=12.25)]
    path = bench_table.write(tmp_path / "out", "bench_x", "Thing", "stride bench-x", {"a": 1},
                             "Measured here.", ["robot", "ms:"], rows,
                             lambda r: [r["robot"], f"{r['ms']:.2f}"])
    tag = bench_table.device_tag()
    assert path == tmp_path / "out" / f"bench_x_{tag}.md"
    assert json.loads((tmp_path / "out" / f"bench_x_{tag}.json").read_text()) == \
        {"env": {"a": 1}, "rows": rows}
    lines = path.read_text().splitlines()
    assert lines[:5] == [f"# Thing ({tag})", "", "Command: `stride bench-x`", "", "Measured here."]
    assert lines[6:] == ["| robot | ms |", "|---|---:|", "| go1 | 1.50 |", "| g1 | 12.25 |"]


def test_a_row_of_the_wrong_width_is_refused():
    with pytest.raises(ValueError, match="1 cells for 2 columns"):
        bench_table.markdown("t", "c", "a", ["x", "y"], [["only one"]])
