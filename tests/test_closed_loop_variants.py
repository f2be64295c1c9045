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
