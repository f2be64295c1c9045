"""A gravity direction told to the Lagrangian prior (``down``): the potential of uniform gravity
along ``down`` is the trained one of the pose seen from a gravity-aligned frame. Checked against
MuJoCo under tilted gravity (with MuJoCo's own potential turned so), against autodiff through the
retraction and by energy balance for the learned prior, in the fused kernels and through the
model interface; the centre-of-mass potential (``"com"``) against its closed form, and trained.
(The planner's ``model_gravity``: ``tests/test_control_closed_loop.py``.)"""

import copy
import dataclasses

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
from precision import assert_close, exact
from test_base_structure import (BASE, MASS, TINY_NET, _configurations, _robot,
                                 train_on_a_known_prior)
from test_lagrangian import _mujoco_energy, _random_states

import stride_jax.dynamics as dyn
from stride_jax.dynamics import integrate, lagrangian, mlp, models, stride
from stride_jax.sim import model as sim_model


def _down(slope_deg=20.0, heading_deg=30.0):
    """Gravity's direction under which a level floor is a slope, uphill along the heading."""
    s, h = np.deg2rad(slope_deg), np.deg2rad(heading_deg)
    return np.array([-np.sin(s) * np.cos(h), -np.sin(s) * np.sin(h), -np.cos(s)])


def test_quat_between_turns_one_direction_onto_another():
    with jax.enable_x64(True):
        for a, b in ((_down(), [0.0, 0.0, -1.0]), ([0.0, 0.0, -1.0], [0.0, 0.0, -1.0]),
                     ([0.0, 0.0, 1.0], [0.0, 0.0, -1.0]), ([1.0, 0.0, 0.0], [-2.0, 0.0, 0.0])):
            r = integrate.quat_to_mat(integrate.quat_between(jnp.asarray(a), jnp.asarray(b)))
            a, b = np.asarray(a) / np.linalg.norm(a), np.asarray(b) / np.linalg.norm(b)
            np.testing.assert_allclose(np.asarray(r) @ a, b, atol=1e-12)
            np.testing.assert_allclose(np.asarray(r) @ np.asarray(r).T, np.eye(3), atol=1e-12)
            assert np.linalg.det(np.asarray(r)) == pytest.approx(1.0)


def test_a_potential_turned_to_a_gravity_direction_is_mujocos_under_that_gravity():
    """MuJoCo's own world-down potential, turned by :func:`lagrangian.gravity_frame`, gives
    through the Euler-Lagrange machinery MuJoCo's bias force under tilted gravity (fails for a
    wrong rotation, quaternion order or base-position turn), which differs from the level one."""
    sm = sim_model.load("go1")
    down = _down()
    tilted = copy.copy(sm.mj)
    tilted.opt.gravity[:] = np.linalg.norm(sm.mj.opt.gravity) * down
    d, level = mujoco.MjData(tilted), mujoco.MjData(sm.mj)
    with jax.enable_x64(True):
        mass, potential = _mujoco_energy(sm.mj)
        turned = lambda q: potential(lagrangian.gravity_frame(q, jnp.asarray(down)))
        terms = jax.jit(lambda q, v: lagrangian.bias_force(mass, turned, q, v, True))
        for q, v in _random_states(sm, np.random.default_rng(0), 4):
            q[:3] = [0.3, -0.2, 0.4]  # the turn is about the world origin: off it, it matters
            for data in (d, level):
                data.qpos[:], data.qvel[:] = q, v
                mujoco.mj_forward(data.model, data)
            b = np.asarray(terms(jnp.asarray(q), jnp.asarray(v))[1])
            scale = np.abs(d.qfrc_bias).max()
            np.testing.assert_allclose(b, d.qfrc_bias, rtol=1e-7, atol=1e-7 * scale)
            assert np.abs(level.qfrc_bias - d.qfrc_bias).max() > 1.0  # the tilt matters


def _lnn(shared=False, structure=True, potential="net"):
    return lagrangian.LNNConfig(net=mlp.MLPConfig(hidden=32, depth=2), mass_init=MASS,
                                shared=shared, base_structure=structure, potential=potential)


# (one network for L and V turns its potential as two do: the shared case runs in `make test-all`)
PRIORS = pytest.mark.parametrize("shared,potential", [
    pytest.param(False, "net", id="two-nets"),
    pytest.param(True, "net", id="shared", marks=pytest.mark.slow),
    pytest.param(False, "com", id="com")])


def _states(n, dtype):
    """``n`` configurations of ``BASE`` (test_base_structure's) and velocities."""
    return (_configurations(BASE, n, dtype),
            2.0 * jax.random.normal(jax.random.key(2), (n, BASE.nv), dtype))


@PRIORS
def test_the_learned_prior_under_a_gravity_direction(shared, potential):
    """``lnn_terms`` with ``down`` equals ``bias_force`` of the turned potential through the
    retraction, conserves energy with it, and is the trained prior for world down; the
    translational gravity force is ``m g`` against ``down``, exactly. Either potential, the
    network's or the centre-of-mass form (``"com"``)."""
    cfg = _lnn(shared, potential=potential)

    @jax.jit  # one program: op by op the first variant took 33 s, jitted 10 (2-core CPU)
    def terms(params, qs, vs, taus, down):
        fast = jax.vmap(lambda q, v: lagrangian.lnn_terms(params, BASE, q, v, cfg,
                                                          down=down))(qs, vs)
        ref = jax.vmap(lambda q, v: lagrangian.lnn_terms_reference(params, BASE, q, v, cfg,
                                                                   down))(qs, vs)
        level = jax.vmap(lambda q, v: lagrangian.lnn_terms(params, BASE, q, v, cfg))(qs, vs)
        world_down = jax.vmap(lambda q, v: lagrangian.lnn_terms(
            params, BASE, q, v, cfg, down=jnp.array([0.0, 0.0, -2.0])))(qs, vs)
        g = jax.vmap(lambda q: lagrangian.gravity(params, BASE, q, cfg, down))(qs)

        def power(q, v, tau):
            M, b = lagrangian.lnn_terms(params, BASE, q, v, cfg, down=down)
            qdd = jnp.linalg.solve(M, tau - b)
            at = lambda s: integrate.retract(q, s * v, True)
            energy = lambda s: (0.5 * (v + s * qdd) @ lagrangian.mass_matrix(
                params, BASE, at(s), cfg) @ (v + s * qdd)
                + lagrangian.potential_energy(params, BASE, at(s), cfg, down))
            return jax.jvp(energy, (0.0,), (1.0,))[1], v @ tau, jnp.abs(v @ b)

        return fast, ref, level, world_down, g, jax.vmap(power)(qs, vs, taus)

    with jax.enable_x64(True):
        down = jnp.asarray(_down(), jnp.float64)
        params = _random_params(cfg, jnp.float64)
        qs, vs = _states(8, jnp.float64)
        taus = jax.random.normal(jax.random.key(3), (8, BASE.nv), jnp.float64)
        fast, ref, level, world_down, g, (de_dt, work, scale) = terms(params, qs, vs, taus, down)
    for a, b, c, w in zip(fast, ref, level, world_down):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(np.asarray(w), np.asarray(c), rtol=1e-12, atol=1e-12)
    assert np.abs(np.asarray(fast[1] - level[1])).max() > 1.0  # the direction matters
    np.testing.assert_allclose(g[:, :3], np.broadcast_to(-MASS * 9.81 * np.asarray(down),
                                                         (8, 3)), rtol=1e-12)
    # (to the rounding of the terms it balances: v . b is the largest)
    np.testing.assert_allclose(de_dt, work, rtol=1e-9, atol=1e-9 * np.asarray(scale).max())


def test_a_gravity_direction_needs_the_floating_base_structure():
    with pytest.raises(ValueError, match="needs a floating base with base_structure"):
        lagrangian.check_down(BASE, _lnn(structure=False), jnp.array([0.0, 0.0, -1.0]))
    fixed = dyn.ModelSpec(nq=2, nv=2, floating_base=False)
    with pytest.raises(ValueError, match="needs a floating base with base_structure"):
        lagrangian.check_down(fixed, _lnn(), jnp.array([0.0, 0.0, -1.0]))
    with pytest.raises(ValueError, match=r"direction \[3\]"):
        lagrangian.check_down(BASE, _lnn(), jnp.zeros(2))
    lagrangian.check_down(BASE, _lnn(structure=False), None)  # nothing told: nothing to check


def _random_params(cfg, dtype):
    """Weights scaled up and none zero (the "com" network's last layer starts at zero)."""
    params = lagrangian.lnn_init(jax.random.key(0), BASE, cfg)
    keys = iter(jax.random.split(jax.random.key(9), 64))
    return jax.tree.map(lambda w: jnp.asarray(2.0 * w + 0.3 * jax.random.normal(
        next(keys), w.shape), dtype), params)


def test_the_com_potential_is_gravitys_multibody_form():
    """With the network's outputs held at a centre-of-mass offset ``c`` and a spring term ``s``
    (its last layer's biases), ``V = m g (p_z + (R c)_z) + s`` and the generalised gravity is
    ``m g`` up on the base and ``m g c x (R^T e_z)`` about it; a joint move changes nothing
    here; told a gravity direction, V is the gravity-aligned pose's, exactly."""
    cfg = _lnn(potential="com")
    c, s = np.array([0.05, -0.02, -0.03]), 0.7
    with jax.enable_x64(True):
        params = jax.tree.map(lambda w: jnp.asarray(w, jnp.float64),
                              lagrangian.lnn_init(jax.random.key(0), BASE, cfg))
        last = sorted(params["potential"]["params"])[-1]
        params["potential"]["params"][last]["bias"] = jnp.asarray(np.r_[c, s])
        qs, _ = _states(6, jnp.float64)
        down = jnp.asarray(_down(), jnp.float64)

        @jax.jit  # one program (op by op: 10 s on a 2-core CPU)
        @jax.vmap
        def terms(q):
            return (lagrangian.potential_energy(params, BASE, q, cfg),
                    lagrangian.gravity(params, BASE, q, cfg),
                    lagrangian.potential_energy(params, BASE, q, cfg, down),
                    lagrangian.potential_energy(params, BASE, lagrangian.gravity_frame(q, down),
                                                cfg),
                    integrate.quat_to_mat(q[3:7]))

        V, g, told, turned, R = terms(qs)
        R = np.asarray(R)
    qs = np.asarray(qs)
    mg = MASS * 9.81
    np.testing.assert_allclose(V, mg * (qs[:, 2] + (R @ c)[:, 2]) + s, rtol=1e-12)
    np.testing.assert_allclose(g[:, :3], np.broadcast_to([0, 0, mg], (6, 3)), rtol=1e-12)
    np.testing.assert_allclose(g[:, 3:6], mg * np.cross(c, R[:, 2, :]), atol=1e-12)
    np.testing.assert_allclose(g[:, 6:], 0.0, atol=1e-12)
    np.testing.assert_allclose(told, turned, rtol=1e-12)


def test_the_com_potential_is_refused_where_it_does_not_apply():
    with pytest.raises(ValueError, match="potential 'sum'"):
        _lnn(potential="sum")
    with pytest.raises(ValueError, match="needs two networks"):
        _lnn(shared=True, potential="com")
    with pytest.raises(ValueError, match="needs two networks"):
        stride.StructuredConfig(base_structure=False, potential="com")
    fixed = dyn.ModelSpec(nq=2, nv=2, floating_base=False)
    with pytest.raises(ValueError, match="needs a floating base"):
        lagrangian.lnn_init(jax.random.key(0), fixed, _lnn(potential="com"))


@PRIORS
def test_fused_kernels_turn_the_potential_as_xla_does(shared, potential, kernels):
    """With ``down`` the per-pass kernels give XLA's terms within the products' rounding (the
    "com" potential: the mass network in the kernel, the potential in XLA); the whole-step
    kernel (world-down gravity built in) gives way to the XLA step, which the planner's model
    then runs."""
    act, states = _robot()
    cfg = stride.StructuredConfig(net=mlp.MLPConfig(hidden=16, depth=1), shared_lnn=shared,
                                  mass_init=MASS, potential=potential)
    xla = models.make("stride", BASE, act, cfg)
    params = jax.tree.map(lambda w: w + 0.05 * jax.random.normal(jax.random.key(1), w.shape),
                          xla.init(jax.random.key(0)))
    down = jnp.asarray(_down(), jnp.float32)
    q, qd = states[:2]
    terms = lambda k: jax.jit(jax.vmap(lambda q, v: lagrangian.lnn_terms(
        params["lnn"], BASE, q, v, cfg.lnn, k, down)))(q, qd)
    with exact():
        ref = terms("xla")
    with kernels():
        out = terms("pallas")
    for name, r, o in zip(("M", "b"), ref, out):
        assert_close(o, r, layers=2 * (cfg.net.depth + 1) + 2, floor=1e-6, err_msg=name)
    if shared:
        whole = models.make("stride", BASE, act, dataclasses.replace(cfg, kernel="pallas-step"))
        told = lambda *a: whole.step(params, *a, down=down)
        assert "stride_fused_step" in str(jax.make_jaxpr(jax.vmap(
            lambda *a: whole.step(params, *a)))(*states))
        assert "stride_fused_step" not in str(jax.make_jaxpr(jax.vmap(told))(*states))


def test_the_model_interface_takes_a_gravity_direction_where_it_can():
    """``step(..., down=)`` of the Lagrangian models: world down is the step as trained, a tilt
    changes it; a next-observation model refuses one (``takes_gravity`` says which)."""
    act, states = _robot()
    cfg = stride.StructuredConfig(net=mlp.MLPConfig(hidden=16, depth=1), mass_init=MASS)
    for name in ("stride", "delan"):
        m = models.make(name, BASE, act, cfg)
        assert models.takes_gravity(m)
        with jax.enable_x64(True):  # the maths, free of float32 summation order
            p = jax.tree.map(lambda w: jnp.asarray(w, jnp.float64), m.init(jax.random.key(0)))
            s64 = [jnp.asarray(x, jnp.float64) for x in states[:3]] + [states[3]]
            told = jax.jit(jax.vmap(lambda down, *a: m.step(p, *a, down=down),
                                    in_axes=(None, 0, 0, 0, 0)))  # one compile for both
            step = lambda down: told(down, *s64)
            plain = jax.jit(jax.vmap(lambda *a: m.step(p, *a)))(*s64)
            level = step(jnp.array([0.0, 0.0, -1.0]))
            tilted = step(jnp.asarray(_down()))
        for a, b in zip(level, plain):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-10, atol=1e-10)
        assert np.abs(np.asarray(tilted[1] - plain[1])).max() > 1e-3
    generic = models.make("stride", BASE, act, dataclasses.replace(cfg, base_structure=False))
    assert not models.takes_gravity(generic)
    onn = models.make("onn", BASE, act, cfg)
    assert not models.takes_gravity(onn)
    p = onn.init(jax.random.key(0))
    with pytest.raises(ValueError, match="onn has no gravity input"):
        onn.step(p, *[s[0] for s in states], down=jnp.array([0.0, 0.0, -1.0]))


@pytest.mark.slow  # the default model trains, saves and loads: test_train.py, test_checkpoint.py
def test_a_com_potential_trains_saves_and_loads(tmp_path):
    """A tiny training run of STRIDE with the centre-of-mass potential on accelerations of a
    known prior: the loss falls, the run records the choice and loads as the same model (told a
    gravity direction too); eval gives it a row of its own."""
    from stride_jax.jobs import eval as table

    cfg = stride.StructuredConfig(net=TINY_NET, mass_init=MASS, potential="com")
    q, qd = train_on_a_known_prior(tmp_path, "stride", cfg)
    back, params = dyn.load(tmp_path)
    assert back.config.potential == "com" and back.config == cfg and models.takes_gravity(back)
    step = back.step(params, q[0], qd[0], jnp.zeros(3), jax.random.key(0),
                     down=jnp.asarray(_down(), jnp.float32))
    assert all(np.isfinite(np.asarray(x)).all() for x in step)
    assert table._label("stride", {"potential": "com"}) == "stride[potential=com]"
    assert table._label("stride", {"potential": "net"}) == "stride"
