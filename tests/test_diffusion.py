"""The diffusion sampler on a known Gaussian: x0 ~ N(m, s^2), whose ideal denoiser is known in
closed form, so a network error can be planted and its effect on a sample measured."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from stride_jax.dynamics import diffusion, mlp

M, S = 1.5, 0.3  # the known distribution of the clean sample (normalised units)


def _ideal(x, s, cfg):
    """The ideal network output at ``x``, level ``s``: E[x0 | x_s] of the Gaussian, in
    ``cfg.target``'s units."""
    ab = diffusion.alpha_bar(s, cfg.steps, cfg.abar_min)
    a, b = jnp.sqrt(ab), jnp.sqrt(1.0 - ab)
    x0 = M + a * S ** 2 / (ab * S ** 2 + 1 - ab) * (x - a * M)
    e = (x - a * x0) / b
    return {"v": a * e - b * x0, "x0": x0, "eps": e}[cfg.target]


def _one_step(cfg, error, n=4000):
    """NFE-1 samples from a denoiser whose output is off by ``error`` (its own units)."""
    predict = lambda x, s: _ideal(x, s, cfg) + error
    keys = jax.random.split(jax.random.key(0), n)
    x_init = jax.vmap(lambda k: jax.random.normal(k, (1,)))(keys)
    return np.asarray(jax.vmap(lambda x, k: diffusion.ddim(predict, x, k, cfg, 1, cfg.eta))(
        x_init, keys))[:, 0]


@pytest.mark.parametrize("target", ["v", "x0"])
def test_one_step_error_stays_within_a_few_sigma(target):
    cfg = diffusion.DiffusionConfig(net=mlp.MLPConfig(hidden=8, depth=1), target=target)
    exact = _one_step(cfg, 0.0)
    assert abs(exact.mean() - M) < 0.05  # the ideal denoiser lands on the distribution's mean
    off = _one_step(cfg, 0.1)  # a network error of 0.1 (a third of sigma)
    assert np.abs(off - M).max() < 3 * S


def test_noise_prediction_on_the_old_schedule_magnifies_the_same_error():
    """What the old parameterisation did (the check above would fail on it): the same 0.1 error
    in the predicted noise lands ~30 sigma away at NFE 1."""
    cfg = diffusion.DiffusionConfig(net=mlp.MLPConfig(hidden=8, depth=1), target="eps",
                                    abar_min=1e-5, clip=10.0)
    assert np.abs(_one_step(cfg, 0.1) - M).min() > 10 * S


def test_schedule_runs_from_clean_to_its_floor():
    cfg = diffusion.DiffusionConfig()
    ab = diffusion.alpha_bar(jnp.arange(cfg.steps + 1.0), cfg.steps, cfg.abar_min)
    np.testing.assert_allclose([ab[0], ab[-1]], [1.0, cfg.abar_min], rtol=1e-5)
    assert bool(jnp.all(jnp.diff(ab) < 0))


@pytest.mark.parametrize("bad", [dict(target="score"), dict(abar_min=0.0)])
def test_bad_diffusion_settings_are_clear_errors(bad):
    with pytest.raises(ValueError, match="target|abar_min"):
        diffusion.DiffusionConfig(**bad)
