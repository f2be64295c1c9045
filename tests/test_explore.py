"""The explorers yield the data the paper needs: gaits, a standing humanoid, the upright saddle."""

import jax
import numpy as np
import pytest

from stride_jax.robots import go1 as go1_lib
from stride_jax.sim import model, randomize, rollout_cpu


def _forced(sm, key, n, T, **overrides):
    """CPU episodes with some explorer parameters overridden (no randomisation)."""
    draw, act, _ = rollout_cpu._jitted(sm)
    rand, params, qpos, qvel = draw(jax.random.split(key, n), T * sm.robot.ctrl_dt)
    params = params._replace(**{k: jax.numpy.full_like(getattr(params, k), v)
                                for k, v in overrides.items()})
    policy = lambda step, q, qd: act(params, step, jax.numpy.asarray(q, "float32"),
                                     jax.numpy.asarray(qd, "float32"), rand.down)
    return rollout_cpu.run(sm, [sm.mj] * n, np.asarray(qpos, float), np.asarray(qvel, float), T,
                           policy)


# Contact agreement between legs (fraction of steps where both are in the same phase) that
# identifies each gait. Legs: 0 FR, 1 FL, 2 RR, 3 RL. Open-loop pronking pitches the trunk, so its
# front and rear pairs agree less than a perfect pronk's would; they still agree far more than a
# trot's (~0.1).
GAIT_CHECKS = {
    "trot": [((0, 3), ">", 0.8), ((1, 2), ">", 0.8), ((0, 1), "<", 0.4)],
    "pronk": [((0, 1), ">", 0.8), ((2, 3), ">", 0.8), ((0, 2), ">", 0.35)],
    "bound": [((0, 1), ">", 0.8), ((2, 3), ">", 0.8), ((0, 2), "<", 0.6)],
    "pace": [((0, 2), ">", 0.7), ((0, 3), "<", 0.4)],
}


@pytest.mark.parametrize("gait", go1_lib.GAITS)
def test_go1_gaits_have_their_footfall_pattern(go1, gait):
    g = go1_lib.GAITS.index(gait)
    recs, valid = _forced(go1, jax.random.key(g), 4, 150, gait=g, noise=0.0, freq=2.0, duty=0.5,
                          lift=0.5, stride=0.15, turn=0.0, lateral=0.0)
    contact = recs.foot_contact[valid]
    assert len(contact) > 200
    for (a, b), op, threshold in GAIT_CHECKS[gait]:
        agree = np.mean(contact[:, a] == contact[:, b])
        assert agree > threshold if op == ">" else agree < threshold, (gait, a, b, agree)


def test_g1_stands_and_shifts_weight(g1):
    recs, valid = _forced(g1, jax.random.key(0), 4, 150, mode=1, sway=0.03, lift=0.0)
    assert valid[:, -1].all(), "the humanoid fell while shifting its weight"
    left, right = recs.foot_force[..., 0], recs.foot_force[..., 1]
    share = left / np.maximum(left + right, 1e-6)
    assert share.max() - share.min() > 0.2  # the load moves from foot to foot


def test_pendulum_data_covers_the_upright():
    sm = model.load("pendulum")
    ep = rollout_cpu.collect(sm, jax.random.key(0), 24, 200)
    q = np.mod(ep.records.q[..., 0], 2 * np.pi)
    assert np.mean(np.abs(q - np.pi) < 0.3) > 0.05
    assert np.mean(q < 0.3) + np.mean(q > 2 * np.pi - 0.3) > 0.05  # and the bottom
    # The hidden torque near the upright pushes one way or the other: a bimodal residual.
    near = np.abs(q - np.pi) < 0.1
    bump = ep.records.qfrc_external[..., 0][near]
    assert (bump > 0.5).any() and (bump < -0.5).any()
    far = np.abs(q - np.pi) > 1.5
    assert np.abs(ep.records.qfrc_external[..., 0][far]).max() < 0.05


def test_randomisation_is_the_same_in_both_backends(go1):
    from mujoco import mjx
    fields = randomize.nominal_fields(go1.mj)
    v = randomize.sample(jax.random.key(1), go1.robot.randomization, 5.0)
    v = v._replace(payload_kg=np.float32(1.5), friction=np.float32(0.5))
    mx = randomize.apply_mjx(mjx.put_model(go1.mj), fields, v, go1.base_body)
    m = randomize.apply_mujoco(go1.mj, fields, v, go1.base_body)
    for k in randomize.FIELDS:
        np.testing.assert_allclose(np.asarray(getattr(mx, k)), getattr(m, k), rtol=1e-6)
    assert m.body_mass[go1.base_body] == pytest.approx(go1.mj.body_mass[go1.base_body] + 1.5)
    foot = go1.foot_geoms[0, 0]
    assert m.geom_friction[foot, 0] == pytest.approx(0.5 * go1.mj.geom_friction[foot, 0])


def test_pushes_reach_the_records(go1):
    ep = rollout_cpu.collect(go1, jax.random.key(2), 4, 100)
    pushed = np.abs(ep.records.qfrc_external[..., :2]).max(-1) > 1.0
    assert pushed.any() and not pushed.all()


def test_the_hidden_payload_sits_on_the_named_body(go1, tmp_path):
    """``Randomization.payload_body``: the data's hidden payload on a named body (the base when
    unnamed); ``stride data --payload-kg-max --payload-body`` carries it into the episodes (the
    same draws on another body make other trajectories) and the dataset's metadata, from which
    the re-simulated continuations read it back; an unknown name fails before any episode."""
    import dataclasses

    from stride_jax.jobs import data as collect
    from stride_jax.sim import continuations

    fields = randomize.nominal_fields(go1.mj)
    r = dataclasses.replace(go1.robot.randomization, payload_body="FR_thigh")
    body = randomize.payload_body_id(go1, r)
    assert body != go1.base_body and randomize.payload_body_id(go1) == go1.base_body
    v = randomize.sample(jax.random.key(1), r, 5.0)._replace(payload_kg=np.float32(1.5))
    m = randomize.apply_mujoco(go1.mj, fields, v, body)
    np.testing.assert_allclose(m.body_mass - go1.mj.body_mass,
                               1.5 * (np.arange(go1.mj.nbody) == body), atol=1e-6)

    cfg = collect.DataConfig(robot="go1", backend="cpu", episodes=3, seconds=0.3,
                             payload_kg_max=5.0, payload_body="FR_thigh", out=str(tmp_path / "a"))
    thigh = collect.generate(cfg)
    base = collect.generate(dataclasses.replace(cfg, payload_body="", out=str(tmp_path / "b")))
    assert thigh.meta["randomization"]["payload_body"] == "FR_thigh"
    assert list(thigh.meta["randomization"]["payload_kg"]) == [0.0, 5.0]
    assert continuations.randomization_of(thigh.meta).payload_body == "FR_thigh"
    q_thigh, q_base = thigh.split("train")["q"], base.split("train")["q"]
    assert np.abs(q_thigh - q_base).max() > 1e-3  # the same draws, on another body
    with pytest.raises(ValueError, match="'backpack' is not a body of 'go1'; its bodies: trunk"):
        collect.generate(dataclasses.replace(cfg, payload_body="backpack"))
    with pytest.raises(ValueError, match="payload_kg_max"):
        collect.generate(dataclasses.replace(cfg, payload_kg_max=-1.0))
