"""Open-loop rollout error: the tangent-space difference, windows, and that training lowers it."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from stride_jax import cli
from stride_jax.dynamics import integrate, models
from stride_jax.eval import rollout
from stride_jax.sim import dataset
from stride_jax.train import job


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


@pytest.mark.parametrize("name", ["delan", "onn"])
def test_training_lowers_the_rollout_error(name, data, tmp_path):
    run = tmp_path / "run"
    cli.main(["train", "--robot", "pendulum", "--model", name, "--preset", "tiny",
              "--steps", "150", "--lr", "3e-3", "--data", str(data), "--out", str(run)])
    ds = dataset.load(data)
    model, params = models.load(run)
    spec = job.spec_from_meta(ds.meta)
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
