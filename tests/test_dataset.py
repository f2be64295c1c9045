import json

import jax
import numpy as np
import pytest

from stride_jax import cli
from stride_jax.sim import dataset, model, rollout_cpu


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    sm = model.load("pendulum")
    ep = rollout_cpu.collect(sm, jax.random.key(0), 6, 30)
    path = tmp_path_factory.mktemp("ds") / "pendulum"
    return dataset.save(path, ep, dict(robot="pendulum", seed=7, ctrl_dt=0.01)), ep


def test_round_trip(saved):
    ds, ep = saved
    loaded = dataset.load(ds.path, robot="pendulum")
    np.testing.assert_array_equal(loaded.arrays["q"], ep.records.q.astype(np.float32))
    np.testing.assert_array_equal(loaded.arrays["valid"], ep.valid)
    np.testing.assert_allclose(loaded.arrays["rand/damping"], ep.rand.damping, rtol=1e-6)
    assert loaded.meta["seed"] == 7 and loaded.meta["versions"]["mujoco"]


def test_non_finite_records_end_validity(saved, tmp_path):
    _, ep = saved
    qdd = np.array(ep.records.qdd)
    qdd[2, 10] = np.nan  # a solver blow-up in the acceleration while the state is still finite
    bad = ep._replace(records=ep.records._replace(qdd=qdd))
    ds = dataset.save(tmp_path / "bad", bad, dict(robot="pendulum", seed=7, ctrl_dt=0.01))
    valid = ds.arrays["valid"]
    assert valid[2, :10].all() and not valid[2, 10:].any()
    assert np.isfinite(np.array(ds.meta["stats"]["qdd"]["std"])).all()
    np.testing.assert_array_equal(np.delete(valid, 2, 0), np.delete(ep.valid, 2, 0))


def test_splits_partition_episodes_and_stats_come_from_train(saved):
    ds, _ = saved
    s = ds.meta["splits"]
    assert sorted(s["train"] + s["val"] + s["test"]) == list(range(6))
    train = ds.split("train")
    np.testing.assert_allclose(ds.stats["qd"]["mean"], train["qd"][train["valid"]].mean(0),
                               rtol=1e-4, atol=1e-6)


def test_missing_file_is_a_clear_error(tmp_path):
    with pytest.raises(dataset.DatasetError, match="missing meta.json"):
        dataset.load(tmp_path)


def _copy(ds, tmp_path):
    dst = tmp_path / "copy"
    dst.mkdir()
    for f in ("arrays.npz", "meta.json"):
        (dst / f).write_bytes((ds.path / f).read_bytes())
    return dst


def test_truncated_file_is_a_clear_error(saved, tmp_path):
    dst = _copy(saved[0], tmp_path)
    data = (dst / "arrays.npz").read_bytes()
    (dst / "arrays.npz").write_bytes(data[: len(data) // 2])
    with pytest.raises(dataset.DatasetError, match="truncated"):
        dataset.load(dst)


def test_corrupt_file_is_a_clear_error(saved, tmp_path):
    dst = _copy(saved[0], tmp_path)
    data = bytearray((dst / "arrays.npz").read_bytes())
    data[len(data) // 2] ^= 0xFF
    (dst / "arrays.npz").write_bytes(bytes(data))
    with pytest.raises(dataset.DatasetError, match="SHA-256"):
        dataset.load(dst)


def test_mismatched_robot_and_version_are_clear_errors(saved, tmp_path):
    with pytest.raises(dataset.DatasetError, match="holds robot 'pendulum', not 'go1'"):
        dataset.load(saved[0].path, robot="go1")
    dst = _copy(saved[0], tmp_path)
    meta = json.loads((dst / "meta.json").read_text())
    meta["format_version"] = 99
    (dst / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(dataset.DatasetError, match="format version 99"):
        dataset.load(dst)


def test_cli_writes_a_dataset(tmp_path, capsys):
    out = tmp_path / "bouncing"
    cli.main(["data", "--robot", "pendulum_bouncing", "--preset", "tiny", "--backend", "cpu",
              "--out", str(out)])
    ds = dataset.load(out, robot="pendulum_bouncing")
    assert ds.meta["n_episodes"] == 8 and ds.meta["n_steps"] == 100
    assert "wrote" in capsys.readouterr().out


def test_cli_rejects_unknown_robot():
    with pytest.raises(SystemExit, match="unknown robot 'spot'"):
        cli.main(["data", "--robot", "spot"])


@pytest.mark.parametrize("args, says", [
    (["--episodes", "2"], "episodes must be >= 3"),
    (["--seconds", "-1"], "seconds=-1.0: need an episode length >= 0"),
    (["--seconds", "0.01"], r"seconds=0.01 is 1 control step\(s\) of 0.01 s: an episode needs at least 2"),
    (["--split", "pmap"], "split='pmap': use one of shard, threads"),
])
def test_cli_rejects_too_little_data(args, says, tmp_path):
    with pytest.raises(SystemExit, match=says):
        cli.main(["data", "--robot", "pendulum", "--preset", "tiny", "--out", str(tmp_path / "d"),
                  *args])
    assert not (tmp_path / "d").exists()


def test_repeated_mjx_collections_reuse_one_compilation():
    """A second collection of the same model and length (data in chunks, a benchmark timing its
    second call) runs the compiled function of the first instead of tracing and compiling again."""
    from stride_jax.sim import rollout_mjx

    sm = model.load("pendulum")
    a = rollout_mjx.collect(sm, jax.random.key(0), 2, 5)
    b = rollout_mjx.collect(sm, jax.random.key(1), 2, 5)
    fn = rollout_mjx.collect_fn(sm, 5)
    assert fn is rollout_mjx.collect_fn(sm, 5) and fn._cache_size() == 1
    assert rollout_mjx.collect_fn(sm, 6) is not fn
    assert not np.array_equal(a.records.q, b.records.q)  # new keys, new episodes
