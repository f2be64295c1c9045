"""Gait parameters: the named gaits' contact schedules have their defining patterns, the
classifiers recover the names (from offsets and from contacts), and the reference is well formed."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from stride_jax.control import gait

FR, FL, RR, RL = range(4)


@pytest.mark.parametrize("name", ["trot", "pronk", "bound", "pace"])
def test_named_gaits_give_their_contact_patterns(name):
    g = gait.named(name, freq=2.0, duty=0.5)
    s = np.asarray(gait.schedule(g, n_steps=100, dt=0.02, clock0=0.013))  # [T, 4]
    # Each leg is down for the duty fraction of the cycle.
    np.testing.assert_allclose(s.mean(0), 0.5, atol=0.03)
    together = {"trot": [(FR, RL), (FL, RR)], "pronk": [(FR, FL), (FR, RR), (FR, RL)],
                "bound": [(FR, FL), (RR, RL)], "pace": [(FR, RR), (FL, RL)]}[name]
    for i, j in together:
        np.testing.assert_array_equal(s[:, i], s[:, j])
    if name == "pronk":
        assert s.all(axis=1).any() and (~s).all(axis=1).any()  # stance together, flight together
    else:  # the other pair alternates with the first: never both pairs down at duty 0.5
        first, second = together
        assert not (s[:, first[0]] & s[:, second[0]]).any()
    assert gait.classify_contacts(s)[0] == name
    assert gait.classify(g.offsets) == (name, 0.0)


def test_classifiers_ignore_a_common_shift_and_noise():
    trot = np.asarray(gait.named("trot").offsets)
    name, dist = gait.classify(trot + 0.37 + np.array([0.02, -0.03, 0.01, 0.0]))
    assert name == "trot" and dist < 0.05
    rng = np.random.default_rng(0)
    s = np.asarray(gait.schedule(gait.named("bound", freq=2.5, duty=0.6), 150, 0.02))
    flips = rng.random(s.shape) < 0.05  # 5% of the contacts misread
    assert gait.classify_contacts(s ^ flips)[0] == "bound"
    with pytest.raises(ValueError, match="contacts must be"):
        gait.classify_contacts(np.zeros((10, 3)))


def test_swing_height_and_reference():
    phases = jnp.array([0.0, 0.25, 0.75, 0.99])
    h = gait.swing_height(phases, 0.5, 0.1)
    np.testing.assert_allclose(h, [0.0, 0.0, 0.1, 0.1 * np.sin(np.pi * 0.98)], atol=1e-6)
    home = jnp.tile(jnp.array([0.0, 0.9, -1.8]), 4)
    cfg = gait.GaitConfig()
    trot = gait.named("trot")
    still = gait.reference(cfg, trot, 0.1, jnp.zeros(3), home)
    walk = jax.vmap(lambda c: gait.reference(cfg, trot, c, jnp.array([1.0, 0, 0]), home))(
        jnp.linspace(0, 1, 50, endpoint=False))
    # Standing still, stance legs hold the home pose; walking sweeps the thighs both ways.
    stance = np.asarray(gait.in_stance(gait.leg_phases(0.1, trot.offsets), trot.duty))
    np.testing.assert_allclose(np.asarray(still).reshape(4, 3)[stance], np.asarray(home).reshape(
        4, 3)[stance], atol=1e-6)
    thigh = np.asarray(walk).reshape(50, 4, 3)[:, :, 1] - 0.9
    assert thigh.max() > 0.05 and thigh.min() < -0.05
    u = gait.join_action(jnp.zeros(12), trot)
    joint, back = gait.split_action(u, 12)
    np.testing.assert_array_equal(back.offsets, trot.offsets)
    with pytest.raises(ValueError, match="gait parameters"):
        gait.split_action(jnp.zeros(15), 12)
    with pytest.raises(ValueError, match="unknown gait"):
        gait.named("gallop")
    with pytest.raises(ValueError, match="duty"):
        gait.GaitConfig(duty=(0.0, 0.5))
