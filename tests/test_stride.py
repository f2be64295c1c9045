"""A tiny STRIDE against a tiny DeLaN on a pendulum whose residual is bimodal at the upright."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from stride_jax.dynamics import lagrangian, mlp, stride
from stride_jax.types import ModelSpec

SPEC = ModelSpec(nq=1, nv=1, floating_base=False, periodic=(True,))
CFG = stride.StructuredConfig(net=mlp.MLPConfig(hidden=64, depth=2), nfe=4)
BUMP, WIDTH = 2.0, 0.4


def _true_qdd(q, qd, tau, s):
    """Unit pendulum (m = l = 1) with damping 0.1 and a hidden +-2 N m bump at the upright."""
    d = jnp.mod(q - jnp.pi + jnp.pi, 2 * jnp.pi) - jnp.pi
    return tau - 9.81 * jnp.sin(q) - 0.1 * qd + s * BUMP * jnp.exp(-0.5 * (d / WIDTH) ** 2)


def _batch(key, n):
    kq, kd, kt, ks = jax.random.split(key, 4)
    q = jax.random.uniform(kq, (n, 1), minval=-jnp.pi, maxval=jnp.pi)
    qd = jax.random.uniform(kd, (n, 1), minval=-4, maxval=4)
    tau = jax.random.uniform(kt, (n, 1), minval=-3, maxval=3)
    s = jnp.where(jax.random.bernoulli(ks, shape=(n, 1)), 1.0, -1.0)
    return q, qd, tau, _true_qdd(q, qd, tau, s)


def _train(residual, compiler_options, steps=2000):
    params = stride.init(jax.random.key(0), SPEC, CFG, residual)
    opt = optax.adam(3e-3)
    state = opt.init(params)

    def batch_loss(p, key):
        key_data, key_loss = jax.random.split(key)
        q, qd, tau, qdd = _batch(key_data, 256)
        keys = jax.random.split(key_loss, 256)
        total, _ = jax.vmap(lambda *a: stride.loss(p, SPEC, CFG, residual, *a))(q, qd, tau, qdd, keys)
        return jnp.mean(total)

    def step(i, carry):
        p, s = carry
        g = jax.grad(batch_loss)(p, jax.random.key(1000 + i))
        u, s = opt.update(g, s)
        return optax.apply_updates(p, u), s

    # every step in one program (2000 steps: run-time bound, and no dispatch per step)
    train = jax.jit(lambda p, s: jax.lax.fori_loop(0, steps, step, (p, s)),
                    compiler_options=compiler_options)
    return train(params, state)[0]


def _samples(params, residual, q, n=1000):
    fn = jax.vmap(lambda k: stride.acceleration(params, SPEC, CFG, residual, jnp.array([q]),
                                                 jnp.zeros(1), jnp.zeros(1), k)[0][0])
    return np.asarray(fn(jax.random.split(jax.random.key(5), n)))


def _w1(a, b):
    """1-D Wasserstein distance between two equal-size samples."""
    return float(np.mean(np.abs(np.sort(a) - np.sort(b))))


@pytest.fixture(scope="module")
def trained(run_time_bound):
    return {"stride": _train("flow", run_time_bound), "delan": _train("mlp", run_time_bound)}


def test_stride_keeps_both_modes_where_delan_averages(trained):
    n = 1000
    truth = np.asarray(_true_qdd(jnp.full(n, jnp.pi), 0.0, 0.0, np.repeat([-1.0, 1.0], n // 2)))
    w_stride = _w1(_samples(trained["stride"], "flow", np.pi, n), truth)
    w_delan = _w1(_samples(trained["delan"], "mlp", np.pi, n), truth)
    assert w_delan > 1.5  # the mean of +-2 N m is ~2 away from either mode
    assert w_stride < 0.5 * w_delan


def test_both_are_accurate_where_the_residual_is_unimodal(trained):
    truth = float(_true_qdd(jnp.array(0.7), 0.0, 0.0, 1.0))
    for name, residual in (("stride", "flow"), ("delan", "mlp")):
        pred = _samples(trained[name], residual, 0.7, 200)
        assert abs(pred.mean() - truth) < 0.3, name
        assert pred.std() < 0.3, name


@pytest.mark.parametrize("robot", ["go1", "g1"])
def test_residual_penalty_spares_exactly_what_stance_feet_can_produce(robot, request):
    """The prior's residual penalty (``stride.non_contact_part``) is blind to any force the
    stance feet produce through their Jacobians, and sees a pure force on the base or a load on a
    swing leg, which no contact can produce."""
    from stride_jax.eval import forces
    from stride_jax.train import dynamics as train_dynamics

    sm = request.getfixturevalue(robot)
    nv, nfeet = sm.mj.nv, sm.nfeet
    rng = np.random.default_rng(0)
    q = np.tile(sm.info.qpos0, (3, 1))
    contact = np.zeros((1, 3, nfeet), bool)
    contact[0, 0, 0] = True  # step 0: one foot down; step 1: airborne
    split = {k: np.zeros((1, 3, n), np.float32) for k, n in
             (("qd", nv), ("tau", nv), ("qdd", nv), ("ctrl", sm.mj.nu))}
    split.update(q=q[None].astype(np.float32), valid=np.ones((1, 3), bool), foot_contact=contact)
    ex = train_dynamics.examples(split, lambda q: forces.foot_jacobians(sm, q))
    jac = ex["contact_jac"]  # [2, nfeet * k, nv]
    k = jac.shape[1] // nfeet
    assert np.abs(jac[0, :k]).sum() > 0 and np.abs(jac[0, k:]).sum() == 0 and not jac[1].any()
    contact_force = jac[0].T @ rng.normal(size=jac.shape[1]).astype(np.float32)
    assert np.abs(stride.non_contact_part(contact_force, jac[0])).max() < (
        1e-3 * np.abs(contact_force).max())
    other_leg = np.zeros(nv, np.float32)
    other_leg[sm.act_dof[-1]] = 10.0  # a joint of another limb
    base_push = np.zeros(nv, np.float32)
    base_push[2] = 100.0  # a pure vertical force on the base
    for f in (other_leg, base_push):
        left = stride.non_contact_part(f, jac[0])
        assert np.linalg.norm(left) > 0.1 * np.linalg.norm(f)
        np.testing.assert_allclose(stride.non_contact_part(f, jac[1]), f)  # free: all of it


@pytest.mark.parametrize("residual", ["flow", "diffusion"])
def test_acceleration_loss_is_deterministic_and_bounded_below(residual):
    """The prior's acceleration loss uses the residual's central sample: the same for every key
    and never negative (the two-sample product it replaced went to -1e7 under training)."""
    params = stride.init(jax.random.key(1), SPEC, CFG, residual)
    params = jax.tree.map(lambda x: 3.0 * x, params)  # a residual with a wide spread
    q, qd, tau, qdd = jnp.array([0.3]), jnp.array([-1.0]), jnp.array([0.5]), jnp.array([2.0])
    accs = [stride.loss(params, SPEC, CFG, residual, q, qd, tau, qdd, jax.random.key(k))[1]["acc"]
            for k in range(3)]
    assert all(float(a) >= 0.0 for a in accs)
    np.testing.assert_allclose(accs, accs[0], rtol=1e-6)


@pytest.mark.parametrize("residual", ["flow", "diffusion"])
def test_acceleration_loss_trains_the_residual_as_algorithm_1(residual):
    """Algorithm 1: the acceleration error back-propagates through the integrated residual sample
    into the residual's own parameters, not only into the prior (the first version stopped it
    there, and prior and flow drifted together along the contact directions)."""
    params = stride.init(jax.random.key(1), SPEC, CFG, residual)
    # A residual that is not exactly zero (its last layer starts at zero).
    params = jax.tree.map(lambda x: x + 0.05 * jax.random.normal(jax.random.key(2), x.shape),
                          params)
    q, qd, tau, qdd = jnp.array([0.3]), jnp.array([-1.0]), jnp.array([0.5]), jnp.array([2.0])

    def acc_grad(cfg):
        g = jax.grad(lambda p: stride.loss(p, SPEC, cfg, residual, q, qd, tau, qdd,
                                           jax.random.key(0))[1]["acc"])(params)
        return float(sum(jnp.sum(jnp.abs(x)) for x in jax.tree.leaves(g["residual"])))

    assert acc_grad(CFG) > 1e-3  # the default, "central"
    assert acc_grad(dataclasses.replace(CFG, acc_through="sample")) > 1e-3
    assert acc_grad(dataclasses.replace(CFG, acc_through="prior")) == 0.0


@pytest.mark.parametrize("residual", ["flow", "diffusion"])
def test_mean_head_takes_the_acceleration_loss_and_the_generator_the_remainder(residual):
    """acc_through="mean": the acceleration loss reaches the mean head and not the generator;
    the generator's own loss reaches the generator and not the head; samples scatter around the
    head's prediction."""
    cfg = dataclasses.replace(CFG, acc_through="mean")
    params = stride.init(jax.random.key(1), SPEC, cfg, residual)
    assert set(params["residual"]) == {"mean", "gen"}
    params = jax.tree.map(lambda x: x + 0.05 * jax.random.normal(jax.random.key(2), x.shape),
                          params)
    q, qd, tau, qdd = jnp.array([0.3]), jnp.array([-1.0]), jnp.array([0.5]), jnp.array([2.0])
    part = "fm" if residual == "flow" else "ddpm"
    size = lambda g, k: float(sum(jnp.sum(jnp.abs(x)) for x in jax.tree.leaves(g["residual"][k])))
    grad = lambda name: jax.grad(lambda p: stride.loss(p, SPEC, cfg, residual, q, qd, tau, qdd,
                                                       jax.random.key(0))[1][name])(params)
    g_acc, g_gen = grad("acc"), grad(part)
    assert size(g_acc, "mean") > 1e-3 and size(g_acc, "gen") == 0.0
    assert size(g_gen, "gen") > 1e-3 and size(g_gen, "mean") == 0.0
    gen = cfg.generator(residual)
    c = stride.context(SPEC, q, qd, tau)
    head = gen.mean(params["residual"], c, 1)
    draws = jax.vmap(lambda k: gen.sample(params["residual"], c, k, 1))(
        jax.random.split(jax.random.key(3), 64))
    assert float(jnp.std(draws)) > 0 and abs(float(jnp.mean(draws) - head[0])) < 3 * float(
        jnp.std(draws))


def test_best_checkpoint_criterion_leaves_the_generator_loss_out():
    params = stride.init(jax.random.key(1), SPEC, CFG, "flow")
    q, qd, tau, qdd = jnp.array([0.3]), jnp.array([-1.0]), jnp.array([0.5]), jnp.array([2.0])
    total, parts = stride.loss(params, SPEC, CFG, "flow", q, qd, tau, qdd, jax.random.key(0))
    np.testing.assert_allclose(parts["select"], parts["acc"] + CFG.residual_weight
                               * parts["res_free"], rtol=1e-6)
    np.testing.assert_allclose(total, parts["select"] + CFG.fm_weight * parts["fm"], rtol=1e-6)


def test_unknown_acc_through_is_a_clear_error():
    with pytest.raises(ValueError, match="acc_through"):
        stride.StructuredConfig(acc_through="everything")


def test_delan_as_published_is_the_prior_alone():
    """``none``: no residual parameters, a zero residual, and the terms give the prior's own
    inverse dynamics: mass @ (qdd - prior) = M qdd - (tau - b)."""
    params = stride.init(jax.random.key(1), SPEC, CFG, "none")
    assert params["residual"] == {}
    q, qd, tau, qdd = jnp.array([0.3]), jnp.array([-1.0]), jnp.array([0.5]), jnp.array([2.0])
    t = stride.terms(params, SPEC, CFG, "none", q, qd, tau, None)
    np.testing.assert_array_equal(t["eps"], 0.0)
    M, b = lagrangian.lnn_terms(params["lnn"], SPEC, q, qd, CFG.lnn)
    np.testing.assert_allclose(t["mass"] @ (qdd - t["prior"]), M @ qdd - (tau - b), rtol=1e-5)
    total, parts = stride.loss(params, SPEC, CFG, "none", q, qd, tau, qdd, jax.random.key(0))
    assert set(parts) == {"acc", "res", "res_free", "select"}
    np.testing.assert_allclose(total, parts["select"], rtol=1e-6)
