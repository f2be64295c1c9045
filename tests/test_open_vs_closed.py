"""experiments/open_vs_closed.py: open-loop metrics of trained models against their planners'
closed-loop tracking, by rank correlation."""

import json

import numpy as np
import pytest


def _run(model, seed, rmse, energy):
    return {"model": model, "seed": seed, "state": {"mean": rmse},
            "distribution": {"mean_of_samples": rmse + 1, "energy": energy, "crps": energy / 2}}


def test_spearman_is_a_rank_correlation_with_a_permutation_p_value(experiment):
    mod = experiment("open_vs_closed")
    x = np.arange(8.0)
    rho, p = mod.spearman(x, x ** 3, permutations=2000)  # monotone: rank correlation 1
    assert rho == pytest.approx(1.0) and p < 0.01
    rho, p = mod.spearman(x, -x, permutations=2000)
    assert rho == pytest.approx(-1.0) and p < 0.01
    rho, p = mod.spearman(x, [3, 1, 4, 1, 5, 9, 2, 6], permutations=2000)
    assert -1 < rho < 1 and p > 0.05
    assert mod.spearman([1, 1, 2, 3], [1, 2, 3, 4], permutations=100)[0] < 1  # ties share a rank


def test_points_join_runs_and_rows_by_kind_and_seed_and_leave_falls_out(tmp_path, experiment):
    mod = experiment("open_vs_closed")
    table = {"runs": [_run(m, s, 10 + i, 0.4 + 0.01 * i) for i, (m, s) in
                      enumerate([(m, s) for m in ("stride", "delan", "onn") for s in (0, 1)])]}
    seeds = {"groups": [
        {"scenario": "push", "model": m, "seeds": [0, 1], "vel_rmse": [0.1 + 0.01 * j, 0.1 + 0.01 * j + 0.005],
         "fell": [False, m == "onn"]} for j, m in enumerate(("stride", "delan", "onn"))]}
    points = mod.join(table, seeds)
    assert len(points) == 5 and not any(p["model"] == "onn" and p["seed"] == 1 for p in points)
    (energy,) = [c for c in mod.correlations(points, 500) if c["metric"] == "energy"]
    assert energy["n"] == 5 and energy["rho"] > 0.8  # the better energy score, the better planner here
    (tp, sp) = tmp_path / "table.json", tmp_path / "seeds.json"
    tp.write_text(json.dumps(table))
    sp.write_text(json.dumps(seeds))
    mod.main(["--pair", f"R={tp}:{sp}", "--out", str(tmp_path / "out"), "--permutations", "200"])
    assert "| R | push | 5 |" in (tmp_path / "out.md").read_text()
    assert (tmp_path / "out.png").stat().st_size > 0
    with pytest.raises(SystemExit, match="does not exist"):
        mod.main(["--pair", f"R={tmp_path / 'missing.json'}:{sp}", "--out", str(tmp_path / "x")])
    # seeds retrained apart: a later table's run replaces the earlier one of the same model and seed
    again = {"runs": [_run("stride", 1, 99, 0.9)]}
    merged = mod.merge_tables([table, again])
    assert len(merged["runs"]) == 6
    assert [r for r in merged["runs"] if (r["model"], r["seed"]) == ("stride", 1)] == again["runs"]
    (ap := tmp_path / "again.json").write_text(json.dumps(again))
    mod.main(["--pair", f"R={tp}+{ap}:{sp}", "--out", str(tmp_path / "both"), "--permutations", "200"])
    both = json.loads((tmp_path / "both.json").read_text())["robots"]["R"]["points"]
    assert [p["energy"] for p in both if (p["model"], p["seed"]) == ("stride", 1)] == [0.9]
