"""The reproduction's cheapest parts end to end (phase portrait, residual allocation) on tiny
pendulum models, plus the distribution distance it rests on. The legged parts (nfe, horizon,
forces) share their evaluation code with these and run in ``make reproduce PRESET=tiny``."""

import dataclasses
import json
import math
import pathlib

import numpy as np
import pytest

from stride_jax.eval import horizon, phase, runs
from stride_paper import claims, figures, layout
from stride_jax.jobs import train as job


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    root = tmp_path_factory.mktemp("repro")
    cfg = dataclasses.replace(
        figures.PRESETS["tiny"], root=str(root), out=str(root / "out"),
        parts="phase,allocation", pendulum_episodes=16, pendulum_seconds=3.0,
        pendulum_steps=100, phase_models="delan,stride", phase_grid=7, phase_worlds=16,
        phase_samples=8, alloc_steps=128)
    summary = figures.run(cfg, "tiny", "pytest", log=lambda s: None)
    return cfg, summary


def test_writes_figures_numbers_and_summary(made):
    cfg, summary = made
    out = pathlib.Path(cfg.out)
    for name in ("phase_portrait.png", "residual_allocation.png", "phase.json",
                 "allocation.json", "summary.json"):
        assert (out / name).stat().st_size > 1000, name
    saved = json.loads((out / "summary.json").read_text())
    assert saved["commands"] == {"phase": "pytest", "allocation": "pytest"}
    assert json.loads((out / "phase.json").read_text())["command"] == "pytest"
    ids = {c["id"]: c for c in saved["claims"]}
    for cid in ("phase_w1_vs_delan", "phase_beats_any_deterministic", "allocation_split"):
        assert ids[cid]["holds"] is not None, cid


def test_phase_portrait_numbers_are_sane(made):
    _, summary = made
    p = summary["phase"]
    floor = p["truth"]["w1_near_deterministic_floor"]
    # The data's residual near the upright is two pushes of 1-2 N m on a ~1 kg m^2 pendulum:
    # the best point mass is that far from the truth.
    assert 0.3 < floor < 3.0, floor
    for name in ("delan", "stride"):
        row = p["models"][name]
        assert all(np.isfinite(v["mean"]) for k, v in row.items() if k != "steps_done"), name
        assert row["field_rmse_normalised"]["mean"] < 1.0, (name, row)  # learned something
    # A point mass cannot beat the floor, nor spread.
    assert p["models"]["delan"]["w1_near"]["mean"] >= 0.95 * floor
    assert p["models"]["delan"]["spread_near"]["mean"] == 0.0
    assert p["models"]["stride"]["spread_near"]["mean"] > 0.0


def test_residual_allocation_numbers_are_sane(made):
    _, summary = made
    share = summary["allocation"]["share"]
    for region in ("free", "contact"):
        assert share[region] is not None, f"no {region} steps in the held-out split"
        assert 0.0 <= share[region]["mean"] <= 1.0
        assert 0.0 <= share[region]["truth"] <= 1.0
    # The simulator's own split: impacts are the wall's constraint force, free swing is not.
    assert share["contact"]["truth"] > share["free"]["truth"] + 0.3


def test_finished_runs_are_reused_not_retrained(made):
    cfg, _ = made
    path = layout.run_dir(cfg.root, "pendulum", "tiny", "stride", 0)
    said = []
    tc = job.TrainConfig(robot="pendulum", model="stride", out=str(path))
    assert layout.ensure_run(tc, train=True, log=said.append) == path
    assert said == []
    missing = layout.run_dir(cfg.root, "pendulum", "tiny", "delan", 7)
    assert layout.ensure_run(dataclasses.replace(tc, out=str(missing)), train=False) is None


def test_wasserstein1_matches_analytic_values():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(4000, 1))
    assert phase.wasserstein1(a, a + 0.7)[0] == pytest.approx(0.7, abs=1e-6)
    two_modes = np.repeat([[-1.0], [1.0]], 500, axis=0)
    assert phase.wasserstein1(np.zeros((1, 1)), two_modes)[0] == pytest.approx(1.0, abs=1e-6)
    assert phase.wasserstein1(two_modes, two_modes)[0] == pytest.approx(0.0, abs=1e-12)


def test_unknown_part_is_a_clear_error(tmp_path):
    with pytest.raises(ValueError, match="unknown parts"):
        figures.run(figures.ReproduceConfig(out=str(tmp_path), parts="phase,tables"), "tiny",
                    "x")


def test_phase_grid_is_centred_on_the_upright():
    q, qd = phase.grid(phase.PhaseConfig(grid=5, q_half=0.5, qd_max=1.0))
    assert q.shape == qd.shape == (5, 5)
    assert q[0, 2] == pytest.approx(math.pi) and qd[2, 0] == pytest.approx(0.0)


def test_horizon_summary_counts_diverged_windows_and_keeps_a_robust_median():
    errs = np.ones((2, 4, 3))  # [samples, windows, horizon]
    errs[0, 0, 2] = np.nan  # one diverged rollout
    errs[1, 1] = 1e9  # one exploding but finite rollout
    s = horizon.summarise(errs)
    assert s["diverged"] == pytest.approx(1 / 8)
    assert s["cumulative_median"] == pytest.approx(3.0)
    assert s["cumulative"] > 1e8  # the mean (Table I's number) is dominated by it
    assert s["per_horizon_median"] == pytest.approx([1.0, 1.0, 1.0])


def test_claims_compare_ratios_with_the_paper():
    row = lambda cum, growth: {"cumulative_mean": cum, "growth_last_over_half": growth,
                               "per_horizon_mean": [0.0] * 30}
    summary = {"horizon": {"table": {"go1": {"stride": row(1.0, 2.0), "delan": row(2.0, 2.0),
                                             "onn": row(0.5, 5.0)}}}}
    c = {x["id"]: x for x in claims.claims(summary)}
    assert c["state_go1_vs_delan"]["ours"] == pytest.approx(0.5)
    assert c["state_go1_vs_delan"]["holds"] is True
    assert c["state_go1_vs_delan"]["paper"]["table"] == pytest.approx(0.932 / 1.326)
    assert c["state_go1_vs_onn"]["holds"] is False
    assert c["abstract_20pct_state_go1"]["ours"] == pytest.approx(2.0)  # vs the best (ONN)
    assert c["growth_go1"]["holds"] is True
    assert c["allocation_split"]["holds"] is None  # not measured
