"""The floating-base structure of the Lagrangian prior and its ablation switch
(``LNNConfig.base_structure``, ``stride train --no-base-structure``).

On (the default): M's translational block is exactly ``m I``, ``V = m g z + V_net`` and neither
network sees the base position; saved runs load and give what they gave before the switch
existed. Off: a generic Lagrangian of the base's coordinates (every entry of L learned, the base
height among the inputs, no exact gravity term). Both give an SPD mass matrix and the
Euler-Lagrange terms of their own Lagrangian; the fused kernels keep XLA's maths for the variant.
"""

import dataclasses
import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from precision import assert_close, exact

import stride_jax.dynamics as dyn
from stride_jax.dynamics import integrate, lagrangian, mlp, models, stride
from stride_jax.train import dynamics as train_dynamics
from stride_jax.train import loop

ROOT = pathlib.Path(__file__).resolve().parents[1]
GOLDEN = ROOT / "tests" / "golden" / "go1_stride_s0_prior.npz"
BASE = dyn.ModelSpec(nq=10, nv=9, floating_base=True)  # a floating base with three joints
MASS = 4.0
VARIANTS = pytest.mark.parametrize("structure", [True, False], ids=["structure", "generic"])


def _lnn(structure: bool, shared: bool = False) -> lagrangian.LNNConfig:
    return lagrangian.LNNConfig(net=mlp.MLPConfig(hidden=32, depth=2), mass_init=MASS,
                                shared=shared, base_structure=structure)


def _params(spec, cfg, scale=2.0, dtype=jnp.float32):
    """Weights scaled up, so that no check is carried by near-zero raw outputs."""
    return jax.tree.map(lambda w: scale * jnp.asarray(w, dtype),
                        lagrangian.lnn_init(jax.random.key(0), spec, cfg))


def _configurations(spec, n, dtype=jnp.float32, seed=1):
    q = jax.random.normal(jax.random.key(seed), (n, spec.nq), dtype)
    q = q.at[:, 2].set(0.3 + 0.1 * q[:, 2])
    return q.at[:, 3:7].set(q[:, 3:7] / jnp.linalg.norm(q[:, 3:7], axis=1, keepdims=True))


def test_default_keeps_saved_runs_as_they_were():
    """A run saved before the switch existed (``model.json`` without ``base_structure``) loads
    with the structure and gives, at fixed states, the mass matrix, bias force and acceleration
    the code before the switch gave (``GOLDEN``, written by that code: ``python
    tests/test_base_structure.py`` at commit e7a396c; bitwise equal on the machine that made it)."""
    run = ROOT / "results" / "models" / "go1" / "stride-s0"
    assert "base_structure" not in (run / "model.json").read_text()
    model, params = dyn.load(run)
    assert model.config.base_structure and "log_mass" not in params["lnn"]
    want = np.load(GOLDEN)
    got = _golden_outputs(model, params)
    for k in ("M", "b", "acc"):
        np.testing.assert_allclose(got[k], want[k], rtol=1e-5, atol=1e-5 * np.abs(want[k]).max(),
                                   err_msg=k)
    np.testing.assert_allclose(got["M"][:, :3, :3], np.broadcast_to(
        (model.config.mass_init + model.config.diag_floor) * np.eye(3), (3, 3, 3)), rtol=1e-6)


def _golden_outputs(model, params) -> dict:
    spec, n = model.spec, 3
    quat = jax.random.normal(jax.random.key(3), (n, 4))
    quat = quat / jnp.linalg.norm(quat, axis=1, keepdims=True)
    q = jnp.concatenate([jnp.tile(jnp.array([0.1, -0.2, 0.3]), (n, 1)), quat,
                         0.3 * jax.random.normal(jax.random.key(4), (n, spec.nq - 7))], 1)
    qd = jax.random.normal(jax.random.key(5), (n, spec.nv))
    tau = 5 * jax.random.normal(jax.random.key(6), (n, spec.nv))
    keys = jax.random.split(jax.random.key(8), n)
    M, b = jax.jit(jax.vmap(lambda q, v: lagrangian.lnn_terms(params["lnn"], spec, q, v,
                                                              model.config.lnn)))(q, qd)
    acc = jax.jit(jax.vmap(lambda *a: model.acceleration(params, *a)))(q, qd, tau, keys)
    return {"M": np.asarray(M), "b": np.asarray(b), "acc": np.asarray(acc)}


@VARIANTS
def test_mass_matrix_is_spd_and_its_translational_block_as_configured(structure):
    cfg = _lnn(structure)
    with jax.enable_x64(True):
        params = _params(BASE, cfg, dtype=jnp.float64)
        qs = _configurations(BASE, 64, jnp.float64)
        mass = jax.vmap(lambda q: lagrangian.mass_matrix(params, BASE, q, cfg))
        M = np.asarray(mass(qs))
        moved = qs.at[:, :3].add(jnp.array([0.7, -0.4, 0.2]))  # the base elsewhere, higher
        M_moved = np.asarray(mass(moved))
        M_slid = np.asarray(mass(qs.at[:, :2].add(jnp.array([0.7, -0.4]))))
    np.testing.assert_allclose(M, np.swapaxes(M, 1, 2), atol=1e-12)
    assert np.linalg.eigvalsh(M).min() >= cfg.diag_floor * (1 - 1e-6)
    np.testing.assert_allclose(M_slid, M, atol=1e-12)  # never the horizontal position
    block = M[:, :3, :3]
    if structure:
        np.testing.assert_allclose(block, np.broadcast_to((MASS + cfg.diag_floor) * np.eye(3),
                                                          block.shape), rtol=1e-12)
        np.testing.assert_allclose(M_moved, M, atol=1e-12)  # nor the height
    else:
        # learned: not m I, and it changes with the configuration, the base height included
        assert np.abs(block - MASS * np.eye(3)).max() > 0.5
        assert np.abs(block[:, 0, 1]).max() > 1e-2  # off-diagonal translational coupling
        assert np.std(block, axis=0).max() > 1e-2
        assert np.abs(M_moved - M).max() > 1e-3
    n_out = BASE.nv * (BASE.nv + 1) // 2 - (6 if structure else 0)
    assert params["mass"]["params"]["Dense_2"]["kernel"].shape[1] == n_out


@VARIANTS
def test_gravity_is_the_weight_only_with_the_structure(structure):
    """With the structure, dV/dz is exactly m g at any height and orientation; without it V is a
    network of the height (no m g z term), whose slope at init is nowhere near m g."""
    cfg = _lnn(structure)
    params = _params(BASE, cfg)
    qs = _configurations(BASE, 16)
    g = np.asarray(jax.vmap(lambda q: lagrangian.gravity(params, BASE, q, cfg))(qs))
    if structure:
        np.testing.assert_allclose(g[:, :3], np.broadcast_to([0.0, 0.0, MASS * 9.81], (16, 3)),
                                   rtol=1e-5, atol=1e-5)
    else:
        assert np.abs(g[:, 2] - MASS * 9.81).min() > 5.0
        np.testing.assert_allclose(g[:, :2], 0.0, atol=1e-6)  # V never sees x, y
        assert np.abs(g[:, 2]).max() > 1e-3 and np.std(g[:, 2]) > 1e-3  # but does see z
        with pytest.raises(ValueError, match="learn_mass needs base_structure"):
            dataclasses.replace(cfg, learn_mass=True)
        with pytest.raises(ValueError, match="learn_mass needs base_structure"):
            stride.StructuredConfig(base_structure=False, learn_mass=True)


@VARIANTS
@pytest.mark.parametrize("shared", [False, True], ids=["two-nets", "shared"])
def test_euler_lagrange_terms_of_either_lagrangian(structure, shared):
    """``lnn_terms`` (derivatives split at the features, the base height among them when the
    structure is off) equals ``bias_force`` through the retraction, and the terms conserve
    energy: along ``qdd = M^-1 (tau - b)``, ``d/dt (1/2 v^T M v + V) = v . tau`` (fails if the
    dM/dt term or the gravity term disagreed with M and V)."""
    cfg = _lnn(structure, shared)

    @jax.jit  # one program: op by op the first variant took 22 s, jitted 5 (2-core CPU)
    def terms(params, qs, vs, taus):
        fast = jax.vmap(lambda q, v: lagrangian.lnn_terms(params, BASE, q, v, cfg))(qs, vs)
        ref = jax.vmap(lambda q, v: lagrangian.lnn_terms_reference(params, BASE, q, v, cfg))(
            qs, vs)

        def power(q, v, tau):
            M, b = lagrangian.lnn_terms(params, BASE, q, v, cfg)
            qdd = jnp.linalg.solve(M, tau - b)
            energy = lambda s: (0.5 * (v + s * qdd) @ lagrangian.mass_matrix(
                params, BASE, integrate.retract(q, s * v, True), cfg) @ (v + s * qdd)
                + lagrangian.potential_energy(params, BASE,
                                              integrate.retract(q, s * v, True), cfg))
            return jax.jvp(energy, (0.0,), (1.0,))[1], v @ tau, jnp.abs(v @ b)

        return fast, ref, jax.vmap(power)(qs, vs, taus)

    with jax.enable_x64(True):
        params = _params(BASE, cfg, dtype=jnp.float64)
        qs = _configurations(BASE, 8, jnp.float64)
        vs = 2.0 * jax.random.normal(jax.random.key(2), (8, BASE.nv), jnp.float64)
        taus = jax.random.normal(jax.random.key(3), (8, BASE.nv), jnp.float64)
        fast, ref, (de_dt, work, scale) = terms(params, qs, vs, taus)
    for a, b in zip(fast, ref):
        assert np.abs(np.asarray(b)).max() > 1e-3
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-9, atol=1e-9)
    assert np.asarray(scale).min() > 1e-2  # the balance is not trivially 0 = 0
    np.testing.assert_allclose(de_dt, work, rtol=1e-9, atol=1e-9 * np.asarray(scale).max())


def _robot():
    act = models.Actuation(dof=(6, 7, 8), kp=(20.0,) * 3, kd=(0.5,) * 3,
                           force_range=((-5.0, 5.0),) * 3, dt=0.01, n_substeps=1)
    n = 16
    q = _configurations(BASE, n, seed=3).at[:, 7:].multiply(0.3)
    qd = 0.5 * jax.random.normal(jax.random.key(4), (n, BASE.nv))
    ctrl = 0.2 * jax.random.normal(jax.random.key(5), (n, 3))
    return act, (q, qd, ctrl, jax.random.split(jax.random.key(2), n))


@pytest.mark.parametrize("kernel", [pytest.param("pallas", marks=pytest.mark.slow), "pallas-step"])
# (pallas: the per-pass kernels the pallas-step case falls back to; against XLA in test_fused.py)
def test_fused_kernels_take_xla_maths_for_the_generic_lagrangian(kernel, kernels):
    """The whole-step kernel's layout is the structured one (L's first rows sqrt(m) I, an
    m g z term): without the structure a ``pallas-step`` model takes the per-pass kernels
    (networks only). Their M and bias force equal XLA's within the products' rounding, and so
    do the steps, within what float32 rounding of the weights moves XLA's own step (a solve
    with M follows)."""
    act, states = _robot()
    cfg = stride.StructuredConfig(net=mlp.MLPConfig(hidden=16, depth=1), shared_lnn=True,
                                  mass_init=MASS, base_structure=False)
    xla = models.make("stride", BASE, act, cfg)
    fast = models.make("stride", BASE, act, dataclasses.replace(cfg, kernel=kernel))
    params = jax.tree.map(lambda w: w + 0.05 * jax.random.normal(jax.random.key(1), w.shape),
                          xla.init(jax.random.key(0)))
    jaxpr = str(jax.make_jaxpr(jax.vmap(lambda *a: fast.step(params, *a)))(*states))
    assert "stride_fused_mlp" in jaxpr and "stride_fused_step" not in jaxpr
    structured = models.make("stride", BASE, act, dataclasses.replace(
        cfg, kernel="pallas-step", base_structure=True))
    p_structured = structured.init(jax.random.key(0))
    assert "stride_fused_step" in str(jax.make_jaxpr(jax.vmap(
        lambda *a: structured.step(p_structured, *a)))(*states))  # the rule, not the robot
    q, qd = states[:2]
    terms = lambda k: jax.jit(jax.vmap(lambda q, v: lagrangian.lnn_terms(
        params["lnn"], BASE, q, v, cfg.lnn, k)))(q, qd)
    step = lambda m, p: jax.jit(jax.vmap(lambda *a: m.step(p, *a)))(*states)
    # every weight one float32 step up: how far rounding at the weights' precision moves XLA's
    # own step through the solve (``rounded`` is the identity in float32 on a CPU)
    ulp = jax.tree.map(lambda w: jnp.nextafter(w, jnp.inf), params)
    with exact():
        ref_terms, ref, moved = terms("xla"), step(xla, params), step(xla, ulp)
    with kernels():
        out_terms, out = terms(kernel), step(fast, params)
    # the features' Jacobian, one network's forward, tangent and transposed passes, then L L^T
    for name, r, o in zip(("M", "b"), ref_terms, out_terms):
        assert_close(o, r, layers=2 * (cfg.net.depth + 1) + 2, floor=1e-6, err_msg=name)
    assert float(jnp.max(jnp.abs(ref[1] - qd))) > 1e-3  # the step moved the state
    for name, r, o, m, s in zip(("q", "qd"), ref, out, moved, (q, qd)):
        assert_close(o - s, r - s, sensitivity=jnp.max(jnp.abs(m - r)), floor=1e-6,
                     err_msg=name)


TINY_NET = mlp.MLPConfig(hidden=16, depth=1)


def train_on_a_known_prior(folder, name: str, cfg: stride.StructuredConfig):
    """A tiny training run of model ``name`` under ``cfg`` (``TINY_NET``) on accelerations of a
    random DeLaN prior on ``BASE``, into ``folder``; checks that the validation acceleration
    error fell and returns ``(q, qd)`` of its examples."""
    act = models.Actuation(dof=(6, 7, 8), kp=None, kd=None, force_range=((0.0, 0.0),) * 3,
                           dt=0.01, n_substeps=1)
    truth = models.make("delan_prior", BASE, act, stride.StructuredConfig(net=TINY_NET,
                                                                          mass_init=MASS))
    t_params = truth.init(jax.random.key(7))
    n = 512
    q = _configurations(BASE, n, seed=8)
    qd = jax.random.normal(jax.random.key(9), (n, BASE.nv))
    tau = 3.0 * jax.random.normal(jax.random.key(10), (n, BASE.nv))
    qdd = jax.vmap(lambda *a: truth.acceleration(t_params, *a, None))(q, qd, tau)
    examples = {"q": q, "qd": qd, "tau": tau, "qdd": qdd}
    split = lambda a, b: {k: np.asarray(x[a:b]) for k, x in examples.items()}
    model = models.make(name, BASE, act, cfg)
    dyn.checkpoint.save_definition(folder, model)
    train_dynamics.train_examples(model.loss, model.init, split(0, 448), split(448, n),
                                  loop.LoopConfig(steps=60, batch=64, lr=3e-3, eval_every=20,
                                                  ckpt_every=20), folder, log=lambda _: None)
    rows = np.genfromtxt(folder / "metrics.csv", delimiter=",", names=True)
    assert np.isfinite(rows["val_loss"]).all() and rows["val_acc"][-1] < rows["val_acc"][0]
    return q, qd


@pytest.mark.slow  # the default model's training and round trip: test_train.py, test_checkpoint.py;
# the switch read from a run folder: test_default_keeps_saved_runs_as_they_were
def test_a_generic_lagrangian_trains_saves_and_loads(tmp_path):
    """A tiny training run of DeLaN without the structure: the loss falls, the run records the
    switch and loads as the same model; eval gives it a row of its own."""
    from stride_jax.jobs import eval as table

    cfg = stride.StructuredConfig(net=TINY_NET, mass_init=MASS, base_structure=False)
    q, _ = train_on_a_known_prior(tmp_path, "delan", cfg)
    back, params = dyn.load(tmp_path)
    assert back.config.base_structure is False and back.config == cfg
    assert "base_structure" in (tmp_path / "model.json").read_text()
    M = dyn.mass_matrix(back, params, q[0])
    assert np.all(np.linalg.eigvalsh(np.asarray(M)) > 0)
    assert table._label("delan", {"base_structure": False}) == "delan[no_base_structure]"
    assert table._label("stride", {"base_structure": True}) == "stride"
    assert table._label("onn", {"base_structure": False}) == "onn"


if __name__ == "__main__":  # writes GOLDEN with the code on the path
    m, p = dyn.load(ROOT / "results" / "models" / "go1" / "stride-s0")
    np.savez_compressed(GOLDEN, **_golden_outputs(m, p))
