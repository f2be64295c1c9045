"""Phase portrait of the 1-DoF pendulum near its unstable upright (the paper's Sec. IV-G figure).

The data's stochastic, bimodal residual near the upright (``robots/pendulum.py``,
``sim/randomize.py``): every episode draws a hidden torque ``s A exp(-d^2 / (2 w^2))`` with ``d``
the wrapped angle from the upright (``q = pi``), ``w = 0.25`` rad, ``A ~ U[1, 2]`` N m and a sign
``s = +-1`` at equal odds, applied as ``qfrc_applied`` (recorded in ``qfrc_external``); joint
damping and dry friction are scaled by ``U[0.5, 2]`` per episode. Given ``(q, qd, tau)`` the next
acceleration near the upright is therefore one of two pushes of opposite sign (which way the
pendulum falls), and a mean regressor predicts their average: the averaging bias of Sec. III-E.

What is computed, on a ``(q, qd)`` grid around ``(pi, 0)`` with zero torque command:

* the **vector field** ``(qd, a)`` with ``a = (qd' - qd) / dt`` the mean acceleration over one
  control period: the ground truth from MuJoCo over ``worlds`` draws of the hidden randomisation
  (exactly the data's distribution of episodes), each model from ``samples`` latent draws
  (deterministic models: one);
* **trajectories** from a few starts near the upright: the truth under either sign of the bump
  (nominal damping, ``A = 1.5`` N m), each model's open-loop rollouts (stochastic models: several
  latent draws each);
* the **distribution match** near the upright (``|q - pi| <= near_q``, ``|qd| <= near_qd``): the
  1-Wasserstein distance (rad/s^2) between a model's one-step accelerations and the truth's, per
  state, averaged. Its floor for *any* deterministic model is the truth's mean absolute deviation
  (the distance of the best point mass, the conditional median); a ratio below one is only
  reachable by a model of the distribution.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from stride_jax.eval.runs import LoadedRun
from stride_jax.sim import model as sim_model
from stride_jax.sim import randomize, rollout_cpu


@dataclasses.dataclass(frozen=True)
class PhaseConfig:
    """Attributes:
      q_half: the grid spans ``pi +- q_half`` (rad).
      qd_max: and ``qd in [-qd_max, qd_max]`` (rad/s).
      grid: points per axis.
      worlds: ground-truth draws of the hidden randomisation per state.
      samples: latent draws per state of a stochastic model (also the probe histograms').
      near_q, near_qd: the near-upright region of the distribution match (rad, rad/s).
      traj_steps: control steps of each trajectory.
      traj_samples: rollouts per start of a stochastic model.
      bump_nm: the bump amplitude of the ground-truth trajectories (N m).
      seed: every draw.
    """

    q_half: float = 1.0
    qd_max: float = 2.0
    grid: int = 21
    worlds: int = 256
    samples: int = 128
    near_q: float = 0.3
    near_qd: float = 1.0
    traj_steps: int = 80
    traj_samples: int = 8
    bump_nm: float = 1.5
    seed: int = 0


RESIDUAL = ("Hidden, per episode (robots/pendulum.py, sim/randomize.py): a torque s * A * "
            "exp(-d^2 / (2 * 0.25^2)) on the hinge, d the wrapped angle from the upright (rad), "
            "A ~ U[1, 2] N m, s = +1 or -1 at equal odds, applied as qfrc_applied (recorded in "
            "qfrc_external); joint damping and dry friction scaled by U[0.5, 2]. Near the upright "
            "the residual given (q, qd, tau) is one of two opposite pushes: bimodal.")
# Trajectory starts (q, qd): just off the upright either side, and two swings that barely reach it.
STARTS = ((math.pi + 0.05, 0.0), (math.pi - 0.05, 0.0), (math.pi + 0.45, -1.3),
          (math.pi - 0.45, 1.3))
# States whose one-step acceleration distribution the figure shows: (q, qd).
PROBES = ((math.pi, 0.0), (math.pi + 0.1, 0.0), (math.pi - 0.1, 0.5))


def grid(cfg: PhaseConfig) -> tuple[np.ndarray, np.ndarray]:
    """``(q [G, G], qd [G, G])``, ``meshgrid`` order (rows: qd, columns: q)."""
    q = math.pi + np.linspace(-cfg.q_half, cfg.q_half, cfg.grid)
    qd = np.linspace(-cfg.qd_max, cfg.qd_max, cfg.grid)
    return np.meshgrid(q, qd)


@functools.lru_cache(maxsize=None)
def _disturbance(sm: sim_model.SimModel):
    r, nv = sm.robot.randomization, sm.mj.nv
    return jax.jit(jax.vmap(lambda v, t, q: randomize.disturbance(v, r, t, q, nv)))


def _disturb_fn(sm, rand: randomize.RandValues):
    fn = _disturbance(sm)
    return lambda t, q: fn(rand, jnp.asarray(t, jnp.float32), jnp.asarray(q, jnp.float32))


def true_accelerations(sm: sim_model.SimModel, q: np.ndarray, qd: np.ndarray, worlds: int,
                       key: jax.Array) -> np.ndarray:
    """``[W, N]`` MuJoCo accelerations (rad/s^2) at states ``q, qd [N]`` under zero command, one
    row per draw of the hidden randomisation (damping, dry friction, the signed upright bump).
    The pendulum integrates one Euler step per control period, so ``qacc`` at the state *is*
    the period's mean acceleration ``(qd' - qd) / dt``."""
    if sm.n_substeps != 1:
        raise ValueError(f"{sm.robot.name}: expected one substep per control step")
    n = len(q)
    rand = jax.vmap(lambda k: randomize.sample(k, sm.robot.randomization, sm.robot.episode_s))(
        jax.random.split(key, worlds))
    rand_np = jax.tree.map(np.asarray, rand)
    per_world, _ = rollout_cpu.randomized_worlds(sm, sm.robot.randomization, rand_np)
    models = [m for m in per_world for _ in range(n)]  # references, not copies
    tiled = jax.tree.map(lambda a: np.repeat(a, n, axis=0), rand_np)
    recs, _ = rollout_cpu.run(sm, models, np.tile(q, worlds)[:, None],
                              np.tile(qd, worlds)[:, None], 1,
                              lambda step, qq, qv: np.zeros((len(qq), sm.mj.nu)),
                              _disturb_fn(sm, tiled))
    return np.asarray(recs.qdd[:, 0, 0], np.float64).reshape(worlds, n)


def true_trajectories(sm: sim_model.SimModel, starts: np.ndarray, steps: int, bump_nm: float
                      ) -> tuple[np.ndarray, np.ndarray]:
    """``(q, qd)``, each ``[2, K, T]``: MuJoCo trajectories from ``starts [K, 2]`` under zero
    command with the bump's sign + (index 0) and - (index 1), nominal damping and friction."""
    k = len(starts)
    sign = np.repeat([1.0, -1.0], k)
    one, zero = np.ones(2 * k), np.zeros(2 * k)
    rand = randomize.RandValues(friction=one, softness=one, payload_kg=zero, damping=one,
                                frictionloss=one, bump_nm=sign * bump_nm, push_t=zero,
                                push_s=zero, push_force=np.zeros((2 * k, 3)),
                                extra_push_t=np.zeros((2 * k, 0)),
                                extra_push_s=np.zeros((2 * k, 0)),
                                extra_push_force=np.zeros((2 * k, 0, 3)),
                                terrain_seed=np.zeros(2 * k, np.uint32),
                                down=np.tile([0.0, 0.0, -1.0], (2 * k, 1)))
    recs, _ = rollout_cpu.run(sm, [sm.mj] * (2 * k), np.tile(starts[:, :1], (2, 1)),
                              np.tile(starts[:, 1:], (2, 1)), steps,
                              lambda step, qq, qv: np.zeros((len(qq), sm.mj.nu)),
                              _disturb_fn(sm, rand))
    return (np.asarray(recs.q[..., 0]).reshape(2, k, steps),
            np.asarray(recs.qd[..., 0]).reshape(2, k, steps))


def model_accelerations(run: LoadedRun, q: np.ndarray, qd: np.ndarray, samples: int,
                        key: jax.Array) -> np.ndarray:
    """``[S, N]`` a model's mean acceleration over one control period, ``(qd' - qd) / dt``, at
    states ``q, qd [N]`` under zero command (``S = 1`` for deterministic models)."""
    model, dt = run.model, run.ds.meta["ctrl_dt"]
    nu = len(run.ds.meta["act_dof"])
    s = samples if model.stochastic else 1

    @jax.jit
    def fn(params, q, qd, keys):
        def one(q, qd, k):
            return model.step(params, q[None], qd[None], jnp.zeros(nu), k)[1][0]
        return jax.vmap(lambda k: jax.vmap(one)(q, qd, jax.random.split(k, len(q))))(keys)

    qd_next = fn(run.params, jnp.asarray(q, jnp.float32), jnp.asarray(qd, jnp.float32),
                 jax.random.split(key, s))
    return (np.asarray(qd_next, np.float64) - qd[None]) / dt


def model_trajectories(run: LoadedRun, starts: np.ndarray, steps: int, samples: int,
                       key: jax.Array) -> tuple[np.ndarray, np.ndarray]:
    """``(q, qd)``, each ``[S, K, T]``: open-loop rollouts from ``starts [K, 2]`` under zero
    command (the start included as step 0)."""
    model = run.model
    nu = len(run.ds.meta["act_dof"])
    s = samples if model.stochastic else 1
    ctrls = jnp.zeros((steps - 1, nu))

    @jax.jit
    def fn(params, starts, keys):
        def one(x0, k):
            qs, qds = model.rollout(params, x0[:1], x0[1:], ctrls, k)
            return jnp.concatenate([x0[:1], qs[:, 0]]), jnp.concatenate([x0[1:], qds[:, 0]])
        return jax.vmap(lambda k: jax.vmap(one)(starts, jax.random.split(k, len(starts))))(keys)

    q, qd = fn(run.params, jnp.asarray(starts, jnp.float32), jax.random.split(key, s))
    return np.asarray(q), np.asarray(qd)


def wasserstein1(a: np.ndarray, b: np.ndarray, levels: int = 256) -> np.ndarray:
    """``[N]`` 1-Wasserstein distance between the empirical distributions ``a [Sa, N]`` and
    ``b [Sb, N]`` per column: the mean absolute difference of their quantile functions."""
    u = (np.arange(levels) + 0.5) / levels
    return np.abs(np.quantile(a, u, axis=0) - np.quantile(b, u, axis=0)).mean(0)


def evaluate(runs: dict[str, LoadedRun], cfg: PhaseConfig) -> tuple[dict, dict]:
    """``(numbers, arrays)``: per model the field error and the near-upright distribution match
    (see the module docstring), and everything the portrait draws
    (:func:`stride_jax.jobs.show.plot_phase`)."""
    sm = sim_model.load("pendulum")
    key = jax.random.key(cfg.seed)
    k_true, k_model, k_traj = jax.random.split(key, 3)
    Q, QD = grid(cfg)
    probes = np.asarray(PROBES)
    # The grid and the probe states in one batch (one compiled call per model).
    q = np.concatenate([Q.ravel(), probes[:, 0]])
    qd = np.concatenate([QD.ravel(), probes[:, 1]])
    n_grid = Q.size
    truth_all = true_accelerations(sm, q, qd, cfg.worlds, k_true)  # [W, N + P]
    truth = truth_all[:, :n_grid]
    near = (np.abs(Q.ravel() - math.pi) <= cfg.near_q) & (np.abs(QD.ravel()) <= cfg.near_qd)
    floor = np.abs(truth[:, near] - np.median(truth[:, near], 0)).mean(0)  # best point mass
    true_mean = truth.mean(0)
    scale = float(true_mean.std())
    arrays = {"Q": Q, "QD": QD, "field": {"truth": true_mean.reshape(Q.shape)},
              "probes": probes, "probe_samples": {"truth": truth_all[:, n_grid:]},
              "starts": np.asarray(STARTS),
              "traj": {"truth": true_trajectories(sm, np.asarray(STARTS), cfg.traj_steps,
                                                  cfg.bump_nm)}}
    numbers = {"truth": {
        "w1_near_deterministic_floor": float(floor.mean()),
        "near_states": int(near.sum()), "field_std": scale,
        "range_at_upright": float(np.ptp(truth_all[:, n_grid]))}}
    for name, run in runs.items():
        acc_all = model_accelerations(run, q, qd, cfg.samples, k_model)  # [S, N + P]
        acc = acc_all[:, :n_grid]
        w1 = wasserstein1(acc[:, near], truth[:, near])
        rmse = float(np.sqrt(np.mean((acc.mean(0) - true_mean) ** 2)))
        numbers[name] = {
            "field_rmse": rmse, "field_rmse_normalised": rmse / max(scale, 1e-9),
            "w1_near": float(w1.mean()),
            "w1_near_over_floor": float(w1.mean() / max(floor.mean(), 1e-9)),
            "spread_near": float(acc[:, near].std(0).mean()),
            "true_spread_near": float(truth[:, near].std(0).mean()),
            "stochastic": run.model.stochastic, "seed": run.seed, "steps_done": run.steps_done}
        arrays["field"][name] = acc.mean(0).reshape(Q.shape)
        arrays["probe_samples"][name] = acc_all[:, n_grid:]
        arrays["traj"][name] = model_trajectories(run, np.asarray(STARTS), cfg.traj_steps,
                                                  cfg.traj_samples, k_traj)
    return numbers, arrays
