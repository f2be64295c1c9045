"""experiments/closed_loop_variants.py: planners side by side, as the targets count them."""

import json

import pytest


def _row(sc, model, v, fell=False, part=None, ms=None, lat=None):
    return dict(scenario=sc, model=model, vel_rmse=v, fell=fell, part=part, controller_ms=ms,
                latency_steps=lat)


def test_a_variant_is_the_mean_over_seeds_of_their_draws_that_stayed_up(experiment, tmp_path):
    mod = experiment("closed_loop_variants")
    rows = ([_row("rough", "stride", v, ms=37.0, lat=2) for v in (0.07, 0.08)]
            + [_row("rough", "stride_s1", 0.06, ms=38.0, lat=2),
               _row("rough", "stride_s1", 9.0, fell=True, ms=38.0, lat=2),
               _row("push", "stride", 0.05, ms=36.0, lat=2)])
    s = mod.summary(rows)
    assert s["rough"]["per_seed"] == pytest.approx([0.075, 0.06])  # the fall's error left out
    assert s["rough"]["rmse"] == pytest.approx(0.0675)  # seeds weigh alike, not draws
    assert (s["rough"]["falls"], s["rough"]["episodes"]) == (1, 4)
    assert s["rough"]["controller_ms"] == pytest.approx(37.5) and s["push"]["latency_steps"] == 2
    merged = tmp_path / "merged.json"
    merged.write_text(json.dumps({"rows": [_row("push", "policy", 0.07, part="pol"),
                                           _row("push", "stride@x", 0.01, part="x")]}))
    run = tmp_path / "run.json"
    run.write_text(json.dumps({"rows": rows}))
    out = tmp_path / "t.md"
    mod.main([f"policy={merged}:pol", f"late={run}", "--scenarios", "push", "--out", str(out)])
    text = out.read_text()
    assert "| policy | - | 0 | 0.0700 (0.0700) | 0/1 |" in text  # part pol's rows alone
    assert "| late | 36.0 | 2 | 0.0500 (0.0500) | 0/1 |" in text and "rough" not in text
    with pytest.raises(ValueError, match="no rows of part 'nope'"):
        mod.rows_of(f"x={merged}:nope")


def test_a_label_given_twice_pools_its_files_rows(experiment, tmp_path):
    mod = experiment("closed_loop_variants")
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    a.write_text(json.dumps({"rows": [_row("rough", "stride", 0.06), _row("push", "stride", 0.1)]}))
    b.write_text(json.dumps({"rows": [_row("soft", "stride", 0.07), _row("rough", "stride", 0.08)]}))
    out = tmp_path / "t.md"
    mod.main([f"v={a}", f"v={b}", "--out", str(out)])
    lines = [ln for ln in out.read_text().splitlines() if ln.startswith("| v |")]
    assert len(lines) == 1  # one variant, every scenario of both files
    assert "0.0700 (0.0700) | 0/2 |" in lines[0]  # rough: both files' draws, one seed
    assert "0.1000 (0.1000)" in lines[0] and "0.0700 (0.0700) | 0/1 |" in lines[0]
