"""Evaluation: the rollout error (tangent differences, windows, training lowers it), contact forces
through Jacobians, and the table that ``stride eval`` writes."""

import json
import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from stride_jax import cli, dynamics
from stride_jax.dynamics import integrate, models
from stride_jax.eval import forces, rollout
from stride_jax.sim import dataset
from stride_jax.sim import model as sim_model


def test_difference_inverts_retract():
    rng = np.random.default_rng(0)
    for _ in range(5):
        q0 = np.concatenate([rng.standard_normal(3), rng.standard_normal(4), rng.standard_normal(5)])
        q0[3:7] /= np.linalg.norm(q0[3:7])
        dv = 0.5 * rng.standard_normal(11)
        q1 = integrate.retract(jnp.asarray(q0), jnp.asarray(dv), True)
        np.testing.assert_allclose(integrate.difference(q1, jnp.asarray(q0), True), dv, atol=1e-5)


def test_windows_are_fully_valid():
    valid = np.array([[True] * 5 + [False] * 3, [True] * 8])
    starts = rollout.windows(valid, 3, 100)
    assert len(starts) == 2 + 5
    for e, t in starts:
        assert valid[e, t:t + 4].all()
    with pytest.raises(ValueError, match="no window of 9 valid steps"):
        rollout.windows(valid, 8, 10)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    path = tmp_path_factory.mktemp("eval") / "d"
    cli.main(["data", "--robot", "pendulum", "--preset", "tiny", "--out", str(path)])
    return path


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    return tmp_path_factory.mktemp("runs")


@pytest.mark.parametrize("name", ["delan", "onn", "stride"])
def test_training_lowers_the_rollout_error(name, data, runs):
    run = runs / name
    cli.main(["train", "--robot", "pendulum", "--model", name, "--preset", "tiny",
              "--steps", "150", "--lr", "3e-3", "--data", str(data), "--out", str(run)])
    ds = dataset.load(data)
    model, params = dynamics.load(run)
    spec = models.spec_from_meta(ds.meta)
    test = ds.split("val")
    starts = rollout.windows(test["valid"], 10, 64)
    scales = rollout.observation_scales(ds.split("train"), spec, 10)
    key = jax.random.key(0)
    trained = rollout.rollout_errors(model.rollout, params, test, spec, 10, starts, scales, key)
    untrained = rollout.rollout_errors(model.rollout, model.init(jax.random.key(1)), test, spec,
                                       10, starts, scales, key)
    assert np.isfinite(trained).all()
    assert rollout.cumulative_rmse(trained) < 0.5 * rollout.cumulative_rmse(untrained)
    assert trained[:, -1].mean() > trained[:, 0].mean()  # error grows with the horizon


def test_eval_writes_the_table(runs, tmp_path):
    if len(list(runs.iterdir())) < 3:
        pytest.skip("needs the runs trained above")
    out = tmp_path / "res"
    cli.main(["eval", "--runs", f"{runs}/*", "--preset", "tiny", "--out", str(out)])
    d = json.loads((out / "table.json").read_text())
    assert list(d["table"]) == ["stride", "delan", "onn"]  # registry order
    assert d["command"].startswith("stride eval")
    assert d["table"]["onn"]["share_free"] is None  # no residual to share
    share = d["table"]["stride"]["share_free"]["mean"]
    assert 0.0 <= share <= 1.0
    assert all(r["state"]["diverged"] == 0.0 for r in d["runs"])
    md = (out / "table.md").read_text()
    assert "| stride |" in md and "STRIDE/DeLaN state RMSE" in md
    # Distribution scores against the logged and re-simulated futures (cached per dataset).
    for r in d["runs"]:
        dist = r["distribution"]
        assert dist["truths"] == 3 and 0.0 <= dist["coverage"] <= 1.0
        assert np.isfinite(dist["energy"]) and dist["energy"] > 0
    deterministic = {r["model"]: r for r in d["runs"]}["delan"]["distribution"]
    assert deterministic["coverage"] == 0.0 and deterministic["samples"] == 1
    stochastic = {r["model"]: r for r in d["runs"]}["stride"]["distribution"]
    assert stochastic["samples"] == 3 and stochastic["nominal_coverage"] == 0.5
    data_dir = json.loads((runs / "stride" / "config.json").read_text())["dataset"]
    assert list((pathlib.Path(data_dir) / "continuations").glob("*.npz"))
    assert "energy score" in md


def test_eval_records_the_commit_it_started_from(runs, tmp_path, monkeypatch):
    """A checkout that moves on while the evaluation goes does not relabel its table: the code
    is read once, at its start."""
    from stride_jax.jobs import eval as eval_job
    if len(list(runs.iterdir())) < 3:
        pytest.skip("needs the runs trained above")
    checkout, cached = {"commit": "started-here"}, eval_job._cached
    monkeypatch.setattr(eval_job, "code_version", lambda: checkout["commit"])

    def moving(run, cfg):  # the checkout moves as the first run is evaluated
        checkout["commit"] = "moved-on"
        return cached(run, cfg)

    monkeypatch.setattr(eval_job, "_cached", moving)
    cli.main(["eval", "--runs", f"{runs}/*", "--preset", "tiny", "--out", str(tmp_path)])
    assert json.loads((tmp_path / "table.json").read_text())["code"] == "started-here"


def test_merge_replaces_one_models_rows(runs, tmp_path):
    """A model re-evaluated later (e.g. retrained to the full step count) replaces its rows in
    the earlier table; tables of other settings or datasets are refused."""
    if len(list(runs.iterdir())) < 3:
        pytest.skip("needs the runs trained above")
    from stride_jax.jobs import eval as eval_job
    cli.main(["eval", "--runs", f"{runs}/*", "--preset", "tiny", "--out", str(tmp_path / "a")])
    base = json.loads((tmp_path / "a" / "table.json").read_text())
    update = dict(base, command="later", runs=[dict(r) for r in base["runs"] if r["model"] == "onn"])
    update["runs"][0]["state"] = dict(update["runs"][0]["state"], mean=123.0)
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / "table.json").write_text(json.dumps(update))
    eval_job.merge(tmp_path / "a" / "table.json", tmp_path / "b" / "table.json", tmp_path / "m")
    merged = json.loads((tmp_path / "m" / "table.json").read_text())
    assert merged["table"]["onn"]["state"]["mean"] == 123.0
    assert merged["table"]["stride"] == base["table"]["stride"]
    assert "later" in merged["command"] and "| onn |" in (tmp_path / "m" / "table.md").read_text()
    other = dict(update, config=dict(update["config"], horizon=7))
    (tmp_path / "b" / "table.json").write_text(json.dumps(other))
    with pytest.raises(ValueError, match="different settings.*horizon"):
        eval_job.merge(tmp_path / "a" / "table.json", tmp_path / "b" / "table.json", tmp_path / "m")
    moved = dict(update, run_configs={k: dict(v, dataset_sha256="0" * 64)
                                      for k, v in update["run_configs"].items()})
    (tmp_path / "b" / "table.json").write_text(json.dumps(moved))
    with pytest.raises(ValueError, match="different datasets"):
        eval_job.merge(tmp_path / "a" / "table.json", tmp_path / "b" / "table.json", tmp_path / "m")
    eval_job.merge(tmp_path / "a" / "table.json", tmp_path / "b" / "table.json", tmp_path / "m",
                   other_data=True)
    merged = json.loads((tmp_path / "m" / "table.json").read_text())
    assert merged["datasets"]["onn"] == ["000000000000"]
    assert "regenerated dataset" in (tmp_path / "m" / "table.md").read_text()
    eval_job.merge(tmp_path / "m" / "table.json", tmp_path / "b" / "table.json", tmp_path / "m2",
                   other_data=True)  # a merged table merges again
    assert json.loads((tmp_path / "m2" / "table.json").read_text())["code"] == merged["code"]


def test_eval_latents_and_the_divergence_bound(runs, tmp_path):
    """``--latents rollout`` labels the stochastic rows (their own cache file beside
    ``eval.json``); a rollout beyond ``--diverged-above`` counts as diverged (here all)."""
    if len(list(runs.iterdir())) < 3:
        pytest.skip("needs the runs trained above")
    out = tmp_path / "res"
    cli.main(["eval", "--runs", f"{runs}/*", "--preset", "tiny", "--latents", "rollout",
              "--diverged-above", "1e-9", "--out", str(out)])
    d = json.loads((out / "table.json").read_text())
    assert set(d["table"]) == {"stride[latents=rollout]", "delan", "onn"}
    assert all(r["state"]["diverged"] == 1.0 for r in d["runs"])
    assert (runs / "stride" / "eval-latents-rollout.json").is_file()
    with pytest.raises(SystemExit, match="latents must be one of"):
        cli.main(["eval", "--runs", f"{runs}/*", "--preset", "tiny", "--latents", "world",
                  "--out", str(out)])


def test_eval_without_runs_is_a_clear_error(tmp_path):
    with pytest.raises(SystemExit, match="no training runs"):
        cli.main(["eval", "--runs", str(tmp_path / "nothing*")])
    (tmp_path / "killed").mkdir()  # a run killed before its first checkpoint: named
    (tmp_path / "killed" / "model.json").write_text("{}")
    with pytest.raises(SystemExit, match=r"killed'\] have no summary.json"):
        cli.main(["eval", "--runs", str(tmp_path / "*")])


@pytest.mark.parametrize("robot", ["go1", "g1"])
def test_true_residual_maps_to_the_measured_foot_forces(robot, tmp_path):
    """The Jacobian map, fed MuJoCo's own residual, recovers the logged normal forces."""
    path = tmp_path / robot
    cli.main(["data", "--robot", robot, "--preset", "tiny", "--out", str(path)])
    ds = dataset.load(path)
    s = ds.split("train")
    idx = np.argwhere(s["valid"] & s["foot_contact"].any(-1))[:200]
    pick = lambda k: s[k][idx[:, 0], idx[:, 1]]
    sm = sim_model.load(robot)
    jac = forces.foot_jacobians(sm, pick("q"))
    eps = pick("qfrc_passive") + pick("qfrc_constraint") + pick("qfrc_external")
    stance = pick("foot_contact")
    err = forces.normal_force_errors(jac, stance, eps, pick("foot_force"))
    mean_force = pick("foot_force")[stance].mean()
    assert mean_force > 10.0
    assert np.nanmean(err) < 0.15 * mean_force
    # A residual without its contact part does not give the forces.
    wrong = forces.normal_force_errors(jac, stance, pick("qfrc_passive"), pick("foot_force"))
    assert np.nanmean(wrong) > 0.5 * mean_force


def test_training_variants_get_rows_of_their_own():
    from stride_jax.jobs import eval as table
    assert table._label("stride", {}) == "stride"
    assert table._label("stride", {"acc_through": "mean"}) == "stride[acc_through=mean]"
    assert table._label("stride", {"acc_through": "prior", "learn_mass": True}) == \
        "stride[acc_through=prior,learn_mass]"
    assert table._label("delan", {"acc_through": "mean", "learn_mass": True}) == \
        "delan[learn_mass]"  # no generative residual: acc_through does not apply
    assert table._label("onn", {"learn_mass": True}) == "onn"
