"""The one interface: every model inits, steps, rolls out under jit and vmap, and refuses bad input."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from stride_jax.dynamics import mlp, models, stride
from stride_jax.types import ModelSpec

SPEC = ModelSpec(nq=8, nv=7, floating_base=True)  # a floating base with one joint
ACT = models.Actuation(dof=(6,), kp=(20.0,), kd=(0.5,), force_range=((-5.0, 5.0),), dt=0.005,
                       n_substeps=2)
CFG = stride.StructuredConfig(net=mlp.MLPConfig(hidden=16, depth=1), nfe=2)
Q0 = jnp.zeros(8).at[2].set(0.3).at[3].set(1.0)


@pytest.mark.parametrize("name", list(models.MODELS) + ["stride-shared"])
def test_every_model_jits_vmaps_and_rolls_out(name):
    """(``stride-shared``: STRIDE with one network for L and V.)"""
    shared = name.endswith("-shared")
    model = models.make(name.removesuffix("-shared"), SPEC, ACT,
                        dataclasses.replace(CFG, shared_lnn=shared))
    params = model.init(jax.random.key(0))
    # Perturb the zero-initialised last layers so that outputs depend on inputs and keys.
    params = jax.tree.map(lambda w: w + 0.05 * jax.random.normal(jax.random.key(1), w.shape),
                          params)
    ctrls = 0.1 * jnp.ones((5, 1))
    keys = jax.random.split(jax.random.key(2), 3)
    roll = jax.jit(jax.vmap(model.rollout, in_axes=(None, None, None, None, 0)))
    qs, qds = roll(params, Q0, jnp.zeros(7), ctrls, keys)
    assert qs.shape == (3, 5, 8) and qds.shape == (3, 5, 7)
    assert np.isfinite(np.asarray(qs)).all()
    np.testing.assert_allclose(np.linalg.norm(qs[..., 3:7], axis=-1), 1.0, atol=1e-5)
    spread = float(jnp.std(qds[:, -1], axis=0).max())
    assert (spread > 1e-5) == model.stochastic  # latents change the outcome only when stochastic
    # A rollout is a scan of steps.
    q1, qd1 = jax.jit(model.step)(params, Q0, jnp.zeros(7), ctrls[0], keys[0])
    assert q1.shape == (8,) and qd1.shape == (7,)
    # The training loss differentiates.
    ex = dict(q=Q0, qd=jnp.zeros(7), tau=jnp.zeros(7), qdd=jnp.ones(7), ctrl=ctrls[0],
              q_next=q1, qd_next=qd1)
    grads = jax.grad(lambda p: model.loss(p, ex, keys[0])[0])(params)
    assert all(np.isfinite(np.asarray(g)).all() for g in jax.tree.leaves(grads))
    if model.acceleration is not None:
        terms = model.terms(params, Q0, jnp.zeros(7), jnp.ones(7), keys[0])
        qdd = model.acceleration(params, Q0, jnp.zeros(7), jnp.ones(7), keys[0])
        np.testing.assert_allclose(terms["prior"] + terms["residual"], qdd, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("name", ["stride", "onn"])
def test_bad_inputs_are_clear_errors(name):
    model = models.make(name, SPEC, ACT, CFG)
    params = model.init(jax.random.key(0))
    key = jax.random.key(0)
    with pytest.raises(models.InputError, match=r"q must have shape \(8,\)"):
        model.step(params, jnp.zeros(7), jnp.zeros(7), jnp.zeros(1), key)
    with pytest.raises(models.InputError, match=r"ctrl must have shape \(1,\)"):
        model.step(params, Q0, jnp.zeros(7), jnp.zeros(3), key)
    with pytest.raises(models.InputError, match=r"ctrls must have shape \[H, 1\]"):
        model.rollout(params, Q0, jnp.zeros(7), jnp.zeros(5), key)
    with pytest.raises(models.InputError, match="qd holds NaN"):
        model.step(params, Q0, jnp.full(7, jnp.nan), jnp.zeros(1), key)
    with pytest.raises(models.InputError, match="vmap over the batch"):  # a batch without vmap
        jax.jit(model.step)(params, jnp.tile(Q0, (4, 1)), jnp.zeros((4, 7)), jnp.zeros((4, 1)), key)


def test_unknown_model_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown model 'lstm'; available: stride, delan"):
        models.make("lstm", SPEC, ACT, CFG)
    with pytest.raises(TypeError, match="StructuredConfig"):  # sizes given the wrong way
        models.make("stride", SPEC, ACT, mlp.MLPConfig(16, 1))


def test_a_model_carries_what_it_was_made_from():
    model = models.make("delan_prior", ModelSpec(nq=2, nv=2, floating_base=False))
    assert model.actuation == models.motors(2) and model.config == stride.StructuredConfig()
    assert model.residual == "none" and set(models.DESCRIPTIONS) == set(models.MODELS)
    assert "as published" in models.DESCRIPTIONS["delan_prior"]


def test_implicit_servo_is_the_pd_law_at_the_next_state():
    act = models.Actuation(dof=(6,), kp=(250.0,), kd=(5.0,), force_range=((-100.0, 100.0),),
                           dt=0.004, n_substeps=1)
    q, qd, ctrl = Q0.at[7].set(0.2), jnp.zeros(7).at[6].set(-1.0), jnp.array([0.3])
    tau0, extra = act.implicit(q, qd, ctrl, SPEC)
    m = 1e-3  # a light link: the explicit servo is past Euler's stability limit here
    qdd = tau0[6] / (m + extra[6])
    qd_next = qd[6] + act.dt * qdd
    q_next = q[7] + act.dt * qd_next
    np.testing.assert_allclose(m * qdd, 250.0 * (0.3 - q_next) - 5.0 * qd_next, rtol=1e-4)
    assert act.dt * 5.0 / m > 2  # explicit damping alone would diverge
    # A saturated servo stays explicit.
    tau0, extra = act.implicit(q, qd, jnp.array([10.0]), SPEC)
    assert float(extra[6]) == 0.0 and float(tau0[6]) == 100.0


@pytest.mark.parametrize("name", ["stride", "diffusion"])
def test_latents_per_step_or_held_for_the_rollout(name):
    """``latents="step"`` steps with a fresh key each control step; ``"rollout"`` with the one
    key at every step (so what the residual draws persists); anything else is refused."""
    model = models.make(name, SPEC, ACT, CFG)
    params = jax.tree.map(lambda w: w + 0.05 * jax.random.normal(jax.random.key(1), w.shape),
                          model.init(jax.random.key(0)))
    ctrls, key = 0.1 * jnp.ones((4, 1)), jax.random.key(3)

    step = jax.jit(model.step)

    def stepped(keys):
        q, qd, out = Q0, jnp.zeros(7), []
        for u, k in zip(ctrls, keys):
            q, qd = step(params, q, qd, u, k)
            out.append(qd)
        return np.stack(out)

    for latents, keys in (("step", jax.random.split(key, 4)), ("rollout", [key] * 4)):
        _, qds = jax.jit(model.rollout, static_argnames="latents")(params, Q0, jnp.zeros(7), ctrls,
                                                                   key, latents=latents)
        np.testing.assert_allclose(qds, stepped(keys), rtol=1e-4, atol=1e-6)
    held = models.rollout_keys(key, 3, "rollout")
    assert all(np.array_equal(jax.random.key_data(k), jax.random.key_data(key)) for k in held)
    assert len({tuple(np.asarray(jax.random.key_data(k))) for k in models.rollout_keys(key, 3)}) == 3
    with pytest.raises(ValueError, match="latents must be one of"):
        model.rollout(params, Q0, jnp.zeros(7), ctrls, key, latents="episode")


@pytest.mark.parametrize("name", ["stride", "lnn_diffusion", "diffusion", "onn"])
def test_central_latents_step_with_the_residuals_central_sample(name):
    """``key=None`` is the residual's central sample at every substep (two here), so
    ``latents="central"`` rolls out deterministically, whatever the key, and equals stepping with
    ``None``; a stochastic model's central rollout is not one of its random ones."""
    model = models.make(name, SPEC, ACT, CFG)
    params = jax.tree.map(lambda w: w + 0.05 * jax.random.normal(jax.random.key(1), w.shape),
                          model.init(jax.random.key(0)))
    ctrls = 0.1 * jnp.ones((4, 1))
    roll = jax.jit(model.rollout, static_argnames="latents")
    a = roll(params, Q0, jnp.zeros(7), ctrls, jax.random.key(3), latents="central")[1]
    b = roll(params, Q0, jnp.zeros(7), ctrls, jax.random.key(4), latents="central")[1]
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    q, qd, out = Q0, jnp.zeros(7), []
    for u in ctrls:
        q, qd = jax.jit(model.step)(params, q, qd, u, None)
        out.append(qd)
    np.testing.assert_allclose(np.asarray(a), np.stack(out), rtol=1e-5, atol=1e-7)
    drawn = roll(params, Q0, jnp.zeros(7), ctrls, jax.random.key(3), latents="step")[1]
    assert (float(jnp.abs(drawn - a).max()) > 1e-6) == model.stochastic
    if name == "stride":  # per substep: the prior plus M^-1 times the flow's central residual
        terms = model.terms(params, Q0, jnp.zeros(7), jnp.ones(7), None)
        again = model.terms(params, Q0, jnp.zeros(7), jnp.ones(7), None)
        np.testing.assert_array_equal(np.asarray(terms["residual"]), np.asarray(again["residual"]))


def _one_period(model):
    """``(params, example, q1, qd1)``: the model's parameters with their zero-initialised last
    layers moved (outputs then depend on inputs), one example's state, command and torques, and
    the model's own central step from it (what a logged next state equal to it would be)."""
    params = jax.tree.map(lambda w: w + 0.05 * jax.random.normal(jax.random.key(1), w.shape),
                          model.init(jax.random.key(0)))
    q, qd, ctrl = Q0, 0.1 * jnp.ones(7), jnp.array([0.2])
    q1, qd1 = model.step(params, q, qd, ctrl, None)
    return params, dict(q=q, qd=qd, ctrl=ctrl, tau=jnp.ones(7), qdd=jnp.ones(7)), q1, qd1


@pytest.mark.parametrize("name", ["stride", pytest.param("delan", marks=pytest.mark.slow)])
# (DeLaN's step is STRIDE's structured step without the residual)
def test_transition_loss_is_the_models_own_step_against_the_logged_next_state(name):
    """``transition_weight`` adds, per example, the squared error of the model's one-period step
    (central residual, through both substeps) against ``q_next, qd_next`` in the one-step
    changes' units; zero where the log is the model's own step; it trains both parts."""
    scales = stride.Scales(dq=jnp.full(7, 0.5), dqd=jnp.full(7, 2.0))
    model = models.make(name, SPEC, ACT, dataclasses.replace(CFG, transition_weight=0.5), scales)
    params, ex, q1, qd1 = _one_period(model)
    loss = jax.jit(model.loss)  # one program for both logs (op by op: 18 s on a 2-core CPU)
    own = loss(params, dict(ex, q_next=q1, qd_next=qd1), jax.random.key(2))[1]
    assert float(own["next"]) < 1e-8
    off = dict(ex, q_next=q1.at[7].add(0.1), qd_next=qd1.at[6].add(0.4))
    total, parts = loss(params, off, jax.random.key(2))
    np.testing.assert_allclose(float(parts["next"]), (0.1 / 0.5) ** 2 + (0.4 / 2.0) ** 2,
                               rtol=1e-3)
    plain = jax.jit(models.make(name, SPEC, ACT, CFG, scales).loss)(params, off,
                                                                     jax.random.key(2))
    np.testing.assert_allclose(float(total), float(plain[0]) + 0.5 * float(parts["next"]),
                               rtol=1e-5)
    assert "next" not in plain[1]
    grads = jax.jit(jax.grad(lambda p: model.loss(p, off, jax.random.key(2))[1]["next"]))(params)
    norm = lambda tree: sum(float(jnp.abs(g).sum()) for g in jax.tree.leaves(tree))
    assert norm(grads["lnn"]) > 0 and norm(grads["residual"]) > 0
    with pytest.raises(ValueError, match="transition_weight"):
        dataclasses.replace(CFG, transition_weight=-1.0)


@pytest.mark.parametrize("name", ["stride", pytest.param("delan", marks=pytest.mark.slow), "onn"])
# (DeLaN's one-period losses are STRIDE's structured ones)
def test_base_weight_weighs_the_floating_bases_dofs_in_the_one_period_losses(name):
    """``base_weight``: a floating base's six dofs (pose change and velocity) count this much in
    the one-period losses (the structured models' transition term, ONN's whole loss), each joint
    1; a weight other than 1 without a floating base, without a transition term to weigh, or on
    a generator's loss is refused by name."""
    scales = stride.Scales(dq=jnp.full(7, 0.5), dqd=jnp.full(7, 2.0))
    structured = name != "onn"
    cfg = dataclasses.replace(CFG, transition_weight=0.5) if structured else CFG
    plain = models.make(name, SPEC, ACT, cfg, scales)
    heavy = models.make(name, SPEC, ACT, dataclasses.replace(cfg, base_weight=3.0), scales)
    params, ex, q1, qd1 = _one_period(plain)
    part = "next" if structured else "obs"

    def loss(model, q_next, qd_next):
        return float(model.loss(params, dict(ex, q_next=q_next, qd_next=qd_next), jax.random.key(2))[1][part])

    own = loss(plain, q1, qd1)  # ONN's own step is its loss' zero as well
    base = (q1.at[0].add(0.1), qd1.at[4].add(0.4))  # the base's x position and a rotation rate
    joint = (q1.at[7].add(0.1), qd1.at[6].add(0.4))
    np.testing.assert_allclose(own, 0.0, atol=1e-8)
    expected = (0.1 / 0.5) ** 2 + (0.4 / 2.0) ** 2
    np.testing.assert_allclose(loss(plain, *base), expected, rtol=1e-3)
    np.testing.assert_allclose(loss(heavy, *base), 3.0 * expected, rtol=1e-3)
    np.testing.assert_allclose(loss(heavy, *joint), loss(plain, *joint), rtol=1e-6)
    np.testing.assert_allclose(loss(heavy, *joint), expected, rtol=1e-3)
    fixed = ModelSpec(nq=1, nv=1, floating_base=False)
    with pytest.raises(ValueError, match="no floating base"):
        models.make(name, fixed, models.motors(1), dataclasses.replace(cfg, base_weight=2.0))
    if structured:
        with pytest.raises(ValueError, match="set transition_weight above 0"):
            models.make(name, SPEC, ACT, dataclasses.replace(CFG, base_weight=2.0))
    with pytest.raises(ValueError, match="not weighted per dof"):
        models.make("diffusion", SPEC, ACT, dataclasses.replace(CFG, base_weight=2.0))
    with pytest.raises(ValueError, match="base_weight must be a finite number above 0"):
        dataclasses.replace(CFG, base_weight=0.0)


@pytest.mark.parametrize("name", ["stride", "delan", "onn"])
def test_xla_bf16_kernel_is_the_same_model_with_bfloat16_products(name):
    """``kernel="xla-bf16"``: the same parameters, every network's products in bfloat16 at
    inference -- steps agree with float32 to bfloat16 precision and differ from it -- while the
    training loss stays float32 (equal to the plain model's)."""
    plain = models.make(name, SPEC, ACT, CFG)
    bf16 = models.make(name, SPEC, ACT, dataclasses.replace(CFG, kernel="xla-bf16"))
    params = jax.tree.map(lambda w: w + 0.05 * jax.random.normal(jax.random.key(1), w.shape),
                          plain.init(jax.random.key(0)))
    qd, u, key = 0.3 * jnp.ones(7), 0.1 * jnp.ones(1), jax.random.key(2)
    q1, qd1 = jax.jit(plain.step)(params, Q0, qd, u, key)
    q2, qd2 = jax.jit(bf16.step)(params, Q0, qd, u, key)
    change = float(jnp.linalg.norm(qd1 - qd))
    gap = float(jnp.linalg.norm(qd2 - qd1))
    assert 0 < gap < 0.05 * change, (gap, change)
    ex = dict(q=Q0, qd=qd, tau=jnp.zeros(7), qdd=jnp.ones(7), ctrl=u, q_next=q1, qd_next=qd1)
    np.testing.assert_array_equal(plain.loss(params, ex, key)[0], bf16.loss(params, ex, key)[0])
    assert bf16.config.inference_net.products == "bfloat16" and bf16.config.net.products == "float32"


def test_transition_fraction_computes_the_term_on_an_evenly_spread_share_of_the_minibatch():
    """``transition_fraction``: the model's ``batch_loss`` is the acceleration loss' mean over the
    minibatch plus the weight times the transition term's mean over ``n = ceil(fraction * B)``
    examples spaced evenly over it (``i * B // n``: a random minibatch gives an unbiased estimate,
    and each device's contiguous shard of a data-parallel batch its share); with the whole
    minibatch there is no ``batch_loss`` (the per-example loss' mean is it); the trainer uses
    it for its steps and validates on every example."""
    scales = stride.Scales(dq=jnp.full(7, 0.5), dqd=jnp.full(7, 2.0))
    cfg = dataclasses.replace(CFG, transition_weight=0.5, transition_fraction=0.5)
    model = models.make("stride", SPEC, ACT, cfg, scales)
    assert models.make("stride", SPEC, ACT, dataclasses.replace(cfg, transition_fraction=1.0),
                       scales).batch_loss is None
    params = model.init(jax.random.key(0))
    B = 5
    k = jax.random.split(jax.random.key(1), 6)
    ex = dict(q=jnp.broadcast_to(Q0, (B, 8)) + 0.01 * jax.random.normal(k[0], (B, 8)),
              qd=0.1 * jax.random.normal(k[1], (B, 7)), ctrl=0.2 * jax.random.normal(k[2], (B, 1)),
              tau=jnp.ones((B, 7)), qdd=jax.random.normal(k[3], (B, 7)),
              q_next=jnp.broadcast_to(Q0, (B, 8)), qd_next=jax.random.normal(k[4], (B, 7)))
    keys = jax.random.split(k[5], B)
    total, parts = jax.jit(model.batch_loss)(params, ex, keys)
    per = [model.loss(params, jax.tree.map(lambda a: a[i], ex), keys[i]) for i in range(B)]
    acc = np.mean([float(t) - 0.5 * float(p["next"]) for t, p in per])
    nxt = np.mean([float(per[i][1]["next"]) for i in (0, 1, 3)])  # n = ceil(0.5 * 5) = 3: 0, 1, 3
    np.testing.assert_allclose(float(parts["next"]), nxt, rtol=1e-5)
    np.testing.assert_allclose(float(total), acc + 0.5 * nxt, rtol=1e-5)
    assert abs(nxt - np.mean([float(p["next"]) for _, p in per])) > 1e-3  # a subset, not all
    with pytest.raises(ValueError, match="transition_fraction"):
        dataclasses.replace(CFG, transition_fraction=0.0)
    with pytest.raises(ValueError, match="needs a transition_weight above 0"):
        dataclasses.replace(CFG, transition_weight=0.0, transition_fraction=0.5)


def test_with_substeps_integrates_the_same_accelerations_coarser_or_finer():
    """``models.with_substeps``: the trained substeps give the model's own step (bit for bit),
    the period stays the control period, the steps converge as the substeps get finer (the
    same accelerations, integrated), and a next-observation model, which has none, is refused."""
    model = models.make("delan", SPEC, ACT, CFG)
    params = jax.tree.map(lambda w: w + 0.05 * jax.random.normal(jax.random.key(1), w.shape),
                          model.init(jax.random.key(0)))
    qd0, ctrl, key = 0.3 * jnp.ones(7), jnp.full(1, 0.2), jax.random.key(3)
    step = lambda m: np.concatenate(jax.jit(m.step)(params, Q0, qd0, ctrl, key))
    same = models.with_substeps(model, ACT.n_substeps)
    np.testing.assert_array_equal(step(same), step(model))
    fine = {n: models.with_substeps(model, n) for n in (1, 4, 16, 64)}
    assert all(m.actuation.dt * n == pytest.approx(ACT.dt * ACT.n_substeps)
               for n, m in fine.items())
    gaps = [np.abs(step(fine[n]) - step(fine[64])).max() for n in (1, 4, 16)]
    assert gaps[0] > gaps[1] > gaps[2] > 0  # converging: the same dynamics, integrated finer
    with pytest.raises(ValueError, match="predicts the control period at once"):
        models.with_substeps(models.make("onn", SPEC, ACT, CFG), 1)
    with pytest.raises(ValueError, match="n_substeps=0"):
        models.with_substeps(model, 0)
