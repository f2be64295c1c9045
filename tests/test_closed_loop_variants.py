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
    mod.main([f"m={merged}", "--models", "stride", "--out", str(out)])  # NAME@PART is NAME's
    assert "| m | - | 0 | 0.0100 (0.0100) | 0/1 |" in out.read_text()
    assert "0.0700" not in out.read_text()
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


def test_models_and_the_paired_difference_episode_by_episode(experiment, tmp_path):
    """--models keeps those names' rows; --paired-against differences each variant's episodes
    from the reference's with the same scenario, model, seed and episode, leaving out falls."""
    mod = experiment("closed_loop_variants")

    def r(sc, model, seed, v, fell=False):
        return dict(_row(sc, model, v, fell=fell), seed=seed, episode=seed - 2)

    ref = [r("rough", "stride", 2, 0.06), r("rough", "stride", 3, 0.07),
           r("soft", "stride", 2, 0.05), r("soft", "stride", 3, 0.05, fell=True),
           r("rough", "stride_s1", 2, 0.5)]
    new = [r("rough", "stride", 2, 0.07), r("rough", "stride", 3, 0.09),
           r("soft", "stride", 2, 0.04), r("soft", "stride", 3, 0.04),
           r("rough", "stride_s1", 2, 0.1)]
    p = mod.paired_rows([x for x in new if x["model"] == "stride"], ref)
    assert p["n"] == 3  # the reference's fall leaves its pair out
    assert p["diff"] == pytest.approx((0.01 + 0.02 - 0.01) / 3)
    assert p["lo"] <= p["diff"] <= p["hi"]
    assert p["per_scenario"] == pytest.approx({"rough": 0.015, "soft": -0.01})
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    a.write_text(json.dumps({"rows": ref}))
    b.write_text(json.dumps({"rows": new}))
    out = tmp_path / "t.md"
    mod.main([f"ref={a}", f"new={b}", "--models", "stride", "--paired-against", "ref",
              "--out", str(out)])
    text = out.read_text()
    assert "| new | 3 | +0.0067 [" in text and "| 1 of 2 | rough +0.0150, soft -0.0100 |" in text
    assert "0.5000" not in text  # stride_s1's rows left out
    c = tmp_path / "c.json"  # the policy beside the planners: no pairs, said so
    c.write_text(json.dumps({"rows": [r("rough", "policy", 2, 0.06)]}))
    mod.main([f"ref={a}", f"policy={c}", "--paired-against", "ref", "--out", str(out)])
    assert "| policy | 0 | no episode pairs with one of 'ref'" in out.read_text()
    with pytest.raises(ValueError, match="no such variant"):
        mod.main([f"ref={a}", "--paired-against", "other", "--out", str(out)])
    with pytest.raises(ValueError, match="no rows left"):
        mod.main([f"ref={a}", "--models", "onn", "--out", str(out)])
