"""Sloped data: each episode's gravity tilted under the floor (``Randomization.slope_deg``,
``stride data --slope-deg``), recorded per step (``Record.gravity``), and every consumer told it:
training examples, evaluation windows and continuations, and the models' networks
(``StructuredConfig.gravity_context``). Checked against MuJoCo's own bias force under the
recorded gravity, across both backends, and through the models' interfaces."""

import dataclasses

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from test_base_structure import BASE, TINY_NET, _configurations

from stride_jax.dynamics import models, stride
from stride_jax.jobs import data as collect
from stride_jax.robots import Randomization
from stride_jax.sim import continuations, model, randomize, record, rollout_cpu, rollout_mjx
from stride_jax.train import dynamics as train_dynamics

SLOPE = 25.0


@pytest.fixture(scope="module")
def go1():
    return model.load("go1")


@pytest.fixture(scope="module")
def go1_sloped(go1):
    r = dataclasses.replace(go1.robot.randomization, slope_deg=(0.0, SLOPE))
    return dataclasses.replace(go1, robot=dataclasses.replace(go1.robot, randomization=r))


def test_slope_ranges_are_checked():
    for bad in ((-1.0, 5.0), (10.0, 5.0), (0.0, 90.0), (0.0, float("nan"))):
        with pytest.raises(ValueError, match="slope_deg"):
            Randomization(slope_deg=bad)
    with pytest.raises(ValueError, match="fixed base"):
        collect.generate(collect.DataConfig(robot="pendulum", episodes=3, seconds=0.1,
                                            slope_deg=10.0, out="/nonexistent/never"))
    with pytest.raises(ValueError, match="slope_deg"):
        collect.generate(collect.DataConfig(robot="go1", episodes=3, slope_deg=-5.0,
                                            out="/nonexistent/never"))


def test_a_slope_draw_is_a_unit_tilt_within_range_and_leaves_the_other_draws(go1, go1_sloped):
    keys = jax.random.split(jax.random.key(0), 64)
    level = jax.vmap(lambda k: randomize.sample(k, go1.robot.randomization, 6.0))(keys)
    tilted = jax.vmap(lambda k: randomize.sample(k, go1_sloped.robot.randomization, 6.0))(keys)
    np.testing.assert_array_equal(level.down, np.tile([0.0, 0.0, -1.0], (64, 1)))
    down = np.asarray(tilted.down)
    np.testing.assert_allclose(np.linalg.norm(down, axis=1), 1.0, atol=1e-6)
    tilt = np.degrees(np.arccos(-down[:, 2]))
    assert tilt.max() <= SLOPE + 1e-3 and tilt.max() > 0.8 * SLOPE and tilt.min() < 0.2 * SLOPE
    downhill = np.arctan2(down[:, 1], down[:, 0])
    assert (downhill > 0).any() and (downhill < 0).any()  # every heading
    for f in ("friction", "softness", "payload_kg", "push_t", "push_force", "terrain_seed"):
        np.testing.assert_array_equal(getattr(level, f), getattr(tilted, f))


def _bias_under(m, gravity, q, qd):
    """MuJoCo's ``qfrc_bias`` of ``m`` at ``(q, qd)`` under ``gravity`` (``m`` left as it was)."""
    d = mujoco.MjData(m)
    saved = m.opt.gravity.copy()
    m.opt.gravity[:] = gravity
    try:
        d.qpos[:], d.qvel[:] = q, qd
        mujoco.mj_forward(m, d)
        return d.qfrc_bias.copy()
    finally:
        m.opt.gravity[:] = saved


@pytest.mark.parametrize("backend", ["cpu", pytest.param("mjx", marks=pytest.mark.slow)])  # MJX's
# tilted gravity in `make test`: test_control_closed_loop.py::test_the_controller_senses_the_scenarios_gravity
def test_sloped_records_were_simulated_under_the_gravity_they_carry(go1, go1_sloped, backend):
    """Each record's bias force is MuJoCo's under the record's own gravity (and not under the
    model's level one): the records carry the gravity the step was simulated with."""
    collect_fn = rollout_cpu.collect if backend == "cpu" else rollout_mjx.collect
    ep = collect_fn(go1_sloped, jax.random.key(4), 3, 5)
    g = np.asarray(ep.records.gravity, np.float64)  # [E, T, 3]
    norm = np.linalg.norm(go1.mj.opt.gravity)
    np.testing.assert_allclose(np.linalg.norm(g, axis=-1), norm, rtol=1e-6)
    np.testing.assert_allclose(g / norm, np.broadcast_to(np.asarray(ep.rand.down)[:, None],
                                                         g.shape), atol=1e-6)
    assert np.degrees(np.arccos(-g[..., 2] / norm)).max() > 1.0  # some episode is sloped
    fields, tilted = randomize.nominal_fields(go1.mj), 0
    for e in range(3):  # each episode's randomised model (payload, damping ...), gravity level
        m = randomize.apply_mujoco(go1.mj, fields, jax.tree.map(lambda a: np.asarray(a)[e],
                                                                 ep.rand), go1.base_body)
        q, qd = np.asarray(ep.records.q[e, 2], np.float64), np.asarray(ep.records.qd[e, 2],
                                                                        np.float64)
        rec = np.asarray(ep.records.qfrc_bias[e, 2], np.float64)
        scale = np.abs(rec).max()
        np.testing.assert_allclose(_bias_under(m, g[e, 2], q, qd), rec, atol=2e-4 * scale)
        if np.degrees(np.arccos(-g[e, 2, 2] / norm)) > 3.0:  # the level model's is another
            tilted += 1
            assert np.abs(_bias_under(m, m.opt.gravity, q, qd) - rec).max() > 1e-2 * scale
    assert tilted


def test_level_records_carry_the_models_gravity_and_read_as_level(go1):
    ep = rollout_cpu.collect(go1, jax.random.key(1), 3, 3)
    np.testing.assert_allclose(np.asarray(ep.records.gravity),
                               np.broadcast_to(go1.mj.opt.gravity, (3, 3, 3)), rtol=1e-6)
    arrays = {"gravity": np.asarray(ep.records.gravity), "valid": np.ones((3, 3), bool)}
    assert record.down_of(arrays) is None
    assert record.down_of({"valid": np.ones((3, 3), bool)}) is None  # written before the field
    arrays["gravity"] = arrays["gravity"].copy()
    arrays["gravity"][1] = [0.0, 9.81 * np.sin(0.1), -9.81 * np.cos(0.1)]
    down = record.down_of(arrays)
    assert down.shape == (3, 3, 3)
    np.testing.assert_allclose(down[1, 0], [0.0, np.sin(0.1), -np.cos(0.1)], atol=1e-6)
    np.testing.assert_allclose(down[0, 0], [0.0, 0.0, -1.0])


def test_sloped_data_tells_the_examples_and_level_data_does_not(tmp_path):
    cfg = collect.DataConfig(robot="go1", backend="cpu", episodes=4, seconds=0.2,
                             slope_deg=SLOPE, out=str(tmp_path / "sloped"))
    ds = collect.generate(cfg)
    assert list(ds.meta["randomization"]["slope_deg"]) == [0.0, SLOPE]
    split = ds.split("train")
    ex = train_dynamics.examples(split)
    v = split["valid"][:, :-1] & split["valid"][:, 1:]
    g = split["gravity"][:, :-1][v]
    np.testing.assert_allclose(ex["down"], g / np.linalg.norm(g, axis=1, keepdims=True),
                               atol=1e-6)
    level = collect.generate(dataclasses.replace(cfg, slope_deg=0.0, out=str(tmp_path / "l")))
    assert "down" not in train_dynamics.examples(level.split("train"))


def test_continuations_keep_their_windows_slope(go1_sloped):
    """Re-simulated futures keep the logged window's gravity (observed, not hidden): a robot
    dropped on a steep slope slides its way, and on level ground does not."""
    r = go1_sloped.robot.randomization
    q0 = np.asarray(go1_sloped.info.qpos0, np.float64)[None]
    qd0 = np.zeros((1, go1_sloped.mj.nv))
    ctrl = np.tile(q0[:, 7:], (1, 25, 1))  # the servos hold the home pose
    down = np.array([[np.sin(np.radians(20.0)), 0.0, -np.cos(np.radians(20.0))]])
    kw = dict(t0=np.zeros(1), episode_s=6.0, k=2, key=jax.random.key(0))
    level = continuations.simulate(go1_sloped, dataclasses.replace(r, slope_deg=(0.0, 0.0)),
                                   q0, qd0, ctrl, **kw)
    sloped = continuations.simulate(go1_sloped, r, q0, qd0, ctrl, down=down, **kw)
    drift = lambda c: c.q[0, :, -1, 0] - q0[0, 0]  # x after 0.5 s, per continuation
    assert (drift(sloped) > drift(level) + 0.01).all()


# --------------------------------------------------------------------------------------------
# The models told the slope.

ACT = models.Actuation(dof=(6, 7, 8), kp=(20.0,) * 3, kd=(0.5,) * 3,
                       force_range=((-5.0, 5.0),) * 3, dt=0.01, n_substeps=1)


def _down(deg=20.0):
    return jnp.array([np.sin(np.radians(deg)), 0.0, -np.cos(np.radians(deg))])


def test_gravity_features_are_what_the_base_reads(go1):
    spec = models.spec_from_meta(model.robot_meta(go1))
    q = jnp.asarray(go1.info.qpos0, jnp.float32)
    np.testing.assert_allclose(stride.gravity_features(spec, q, None), [0.0, 0.0, -1.0],
                               atol=1e-6)
    np.testing.assert_allclose(stride.gravity_features(spec, q, _down()), _down(), atol=1e-6)
    yaw = q.at[3:7].set(jnp.array([np.cos(np.pi / 4), 0.0, 0.0, np.sin(np.pi / 4)]))  # 90 deg
    np.testing.assert_allclose(stride.gravity_features(spec, yaw, _down()),
                               [0.0, -np.sin(np.radians(20.0)), -np.cos(np.radians(20.0))],
                               atol=1e-6)
    with pytest.raises(ValueError, match="floating base"):
        stride.gravity_features(models.ModelSpec(nq=2, nv=2, floating_base=False), jnp.zeros(2),
                                 None)


@pytest.mark.parametrize("name", ["stride", "onn"])
def test_a_model_with_gravity_context_is_told_the_slope_and_one_without_is_not(name):
    q = _configurations(BASE, 1, seed=3)[0].at[7:].multiply(0.3)
    qd, ctrl = 0.3 * jnp.ones(BASE.nv), 0.1 * jnp.ones(3)
    told = models.make(name, BASE, ACT, stride.StructuredConfig(net=TINY_NET,
                                                                gravity_context=True))
    plain = models.make(name, BASE, ACT, stride.StructuredConfig(net=TINY_NET))
    p_told, p_plain = told.init(jax.random.key(0)), plain.init(jax.random.key(0))
    assert models.takes_gravity(told)
    assert models.takes_gravity(plain) == (name == "stride")  # the prior takes it anyway
    # the networks see 3 more inputs; untrained residuals output zero (zero last layer): give
    # them weights so that their input matters
    perturb = lambda p: jax.tree.map(lambda a: a + 0.1 * jax.random.normal(
        jax.random.key(a.size), a.shape, a.dtype), p)
    p_told, p_plain = perturb(p_told), perturb(p_plain)
    a = told.step(p_told, q, qd, ctrl, None, down=_down(0.0))
    b = told.step(p_told, q, qd, ctrl, None, down=_down(20.0))
    c = told.step(p_told, q, qd, ctrl, None)  # None: world down
    assert float(jnp.abs(a[1] - b[1]).max()) > 1e-4
    np.testing.assert_allclose(a[1], c[1], atol=1e-5)
    qs, _ = told.rollout(p_told, q, qd, jnp.tile(ctrl, (4, 1)), jax.random.key(1), down=_down())
    assert qs.shape == (4, BASE.nq) and bool(jnp.isfinite(qs).all())
    if name == "onn":
        with pytest.raises(ValueError, match="gravity_context"):
            plain.step(p_plain, q, qd, ctrl, None, down=_down())
        with pytest.raises(ValueError, match="direction"):
            told.step(p_told, q, qd, ctrl, None, down=jnp.ones(2))
    else:  # the residual of the plain model is not told; its prior is
        r0 = plain.terms(p_plain, q, qd, jnp.zeros(BASE.nv), None, down=_down(0.0))["eps"]
        r1 = plain.terms(p_plain, q, qd, jnp.zeros(BASE.nv), None, down=_down(20.0))["eps"]
        np.testing.assert_array_equal(r0, r1)
        t0 = told.terms(p_told, q, qd, jnp.zeros(BASE.nv), None, down=_down(0.0))["eps"]
        t1 = told.terms(p_told, q, qd, jnp.zeros(BASE.nv), None, down=_down(20.0))["eps"]
        assert float(jnp.abs(t0 - t1).max()) > 1e-5


def test_the_whole_step_kernel_is_left_to_models_with_the_papers_context():
    """The fused whole-step kernel builds the residual's context itself, without gravity: a
    gravity-context STRIDE runs the per-pass kernels or XLA instead."""
    cfg = stride.StructuredConfig(net=TINY_NET, shared_lnn=True, kernel="pallas-step")
    assert models._whole_step_applies(BASE, ACT, cfg)
    assert not models._whole_step_applies(BASE, ACT, dataclasses.replace(cfg,
                                                                       gravity_context=True))


@pytest.mark.parametrize("name", ["stride", "onn"])
def test_the_loss_reads_the_examples_gravity(name):
    m = models.make(name, BASE, ACT, stride.StructuredConfig(net=TINY_NET, gravity_context=True,
                                                             transition_weight=1.0))
    p = jax.tree.map(lambda a: a + 0.05, m.init(jax.random.key(0)))
    q = _configurations(BASE, 1, seed=5)[0]
    ex = dict(q=q, qd=0.2 * jnp.ones(BASE.nv), tau=jnp.zeros(BASE.nv), qdd=jnp.ones(BASE.nv),
              ctrl=jnp.zeros(3), q_next=q, qd_next=jnp.zeros(BASE.nv),
              contact_jac=jnp.zeros((0, BASE.nv)))
    level = m.loss(p, ex, jax.random.key(1))[0]
    np.testing.assert_allclose(m.loss(p, dict(ex, down=_down(0.0)), jax.random.key(1))[0], level,
                               rtol=1e-5)
    assert abs(float(m.loss(p, dict(ex, down=_down(20.0)), jax.random.key(1))[0]
                     - float(level))) > 1e-4 * abs(float(level))


@pytest.mark.slow  # the policy senses a slope: test_control_envs.py::test_a_randomised_slope_builds_up_and_the_policy_senses_it
def test_a_policy_explorer_senses_each_worlds_slope(go1_sloped):
    """Walking data on slopes: the policy's observation holds each world's gravity, as its IMU
    would (both backends alike); a blind explorer acts otherwise on the tilted worlds."""
    from stride_jax.control.walk import PolicyExplorer

    class Blind(PolicyExplorer):
        senses_gravity = False

    run = "results/policies/ppo_go1_slope"
    with_explorer = lambda e: dataclasses.replace(go1_sloped, robot=dataclasses.replace(
        go1_sloped.robot, explorer=e))
    sensing, blind = with_explorer(PolicyExplorer(run, 0.0)), with_explorer(Blind(run, 0.0))
    key = jax.random.key(2)
    ep = rollout_cpu.collect(sensing, key, 3, 3)
    down = np.asarray(ep.rand.down)
    explorer, info = sensing.robot.explorer, sensing.info
    for e in range(3):
        params = jax.tree.map(lambda a: jnp.asarray(a)[e], ep.explore)
        told = explorer.act(params, info, 0, ep.records.q[e, 0], ep.records.qd[e, 0],
                            gravity=down[e])
        np.testing.assert_allclose(ep.records.ctrl[e, 0], told, atol=1e-5)
    tilted = np.degrees(np.arccos(-down[:, 2])) > 3.0
    assert tilted.any()
    other = rollout_cpu.collect(blind, key, 3, 3)
    gap = np.abs(other.records.ctrl[:, 0] - ep.records.ctrl[:, 0]).max(-1)
    assert (gap[tilted] > 1e-3).all()
    m = rollout_mjx.collect(sensing, key, 3, 3)
    np.testing.assert_allclose(m.records.ctrl[:, 0], ep.records.ctrl[:, 0], atol=1e-4)


@pytest.mark.slow  # each model's slope context: the tests above
def test_sloped_data_end_to_end_every_model_evaluated_as_it_can_be_told(tmp_path):
    """``stride train`` and ``stride eval`` on sloped data: a model trained with the gravity
    context is evaluated told each window's slope; one trained without it (a next-observation
    model, blind to gravity) is evaluated as trained, not refused."""
    import json

    from stride_jax import cli
    data = tmp_path / "d"
    cli.main(["data", "--robot", "go1", "--backend", "cpu", "--episodes", "4", "--seconds",
              "0.5", "--slope-deg", str(SLOPE), "--out", str(data)])
    for name, extra in (("stride", ["--gravity-context"]), ("onn", [])):
        cli.main(["train", "--robot", "go1", "--model", name, "--preset", "tiny", "--steps", "20",
                  "--data", str(data), "--out", str(tmp_path / "runs" / name), *extra])
    out = tmp_path / "res"
    cli.main(["eval", "--runs", f"{tmp_path / 'runs'}/*", "--preset", "tiny", "--out", str(out)])
    rows = {r["model"]: r for r in json.loads((out / "table.json").read_text())["runs"]}
    assert set(rows) == {"stride", "onn"}
    for r in rows.values():
        assert np.isfinite(r["state"]["mean"])
    assert json.loads((tmp_path / "runs" / "stride" / "model.json").read_text())[
        "config"]["gravity_context"]
