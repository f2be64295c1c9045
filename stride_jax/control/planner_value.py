"""The value trained on the planner's own rollouts, and the model's error where the planner goes
(issue 19, item 2: Dreamer-MPC done right).

The learned value of :mod:`stride_jax.control.learned` was fitted on the PPO policy's states;
the planning diagnosis (``docs/control.md``) found the planner's candidates leave them, and the
terminal value is queried exactly there. Here the planner itself collects the data:

1. **closed loop**: the planner (through its learned dynamics model) drives the MJX robot on the
   nominal ground under random commands of the environment's distribution, ``worlds`` episodes
   side by side; every control step records the real transition ``(x_t, u_t, x_(t+1))``;
2. **along its candidates**: at every step, ``record`` of the planner's candidates (half the
   best-weighted, half drawn at random) are rolled out again through the model, recording the
   imagined states ``x_0 .. x_H`` and actions;
3. **targets**: rewards are the planner's own, ``r = -running_cost`` (the learned reward plus the
   fall cost), and the value's targets are lambda-returns bootstrapped with the value itself
   (:func:`stride_jax.control.learned.lambda_returns`; a candidate's return bootstraps ``V(x_H)``,
   a fall ends a return). Fitted value iteration from the existing value's parameters
   (:func:`stride_jax.control.learned.refit_value`, trained through
   :func:`stride_jax.train.loop.scan_steps`) on the union of both; steps after a fall are left out;
4. **the model's one-step error** (``error_model``): at the same states the simulator replays
   each recorded step from the model's own state, and a small MLP ``err(obs, a)`` regresses the
   model's base-velocity error (m/s), for :attr:`MPPIConfig.error_bound` on a deterministic model
   (``--error-model``), where residual draws cannot disagree.

``collect`` and ``fit`` are pure up to the host-side masks; the Dreamer-MPC ablation
(``stride_jax.jobs.dreamer_mpc.train_value``) runs them and writes ``reward_value.msgpack`` (the
same reward, the new value: a drop-in ``--learned`` file, :func:`stride_jax.control.learned.save`),
``error_model.msgpack`` (:func:`save_error_model`) and ``report.json`` (held-out fit, and the old
and new value's bias on the planner's candidates).
"""

from __future__ import annotations

import dataclasses
import pathlib
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import serialization

from stride_jax.control import envs, episode as episode_lib, learned, mppi, planning as planning_lib
from stride_jax.io import atomic_write
from stride_jax.sim import model as sim_model, rollout_mjx


@dataclasses.dataclass(frozen=True)
class PlannerValueConfig:
    """Data from the planner and the fits.

    Attributes:
      worlds: closed-loop episodes run side by side (nominal ground, random commands).
      seconds: length of each episode (s).
      change_s: a new command from the environment's distribution every this long (s).
      record: candidates recorded per control step (half the best-weighted, half at random).
      holdout: share of the worlds held out for the report.
      rounds: fitted-value-iteration rounds from the existing value.
      steps: Adam steps per round (and for the error model).
      batch: examples per step.
      learning_rate: Adam step size.
      discount: gamma of the targets (set the planner's ``--mppi.discount`` to it).
      lam: lambda of the returns.
      error_model: also fit the one-step error model (the simulator replays every recorded step).
      error_width: hidden width of the error model (2 layers).
      ensemble: value members fitted (1: one value). The first is fitted on all the training
        data; each other on a bootstrap resample of its steps, so that their spread grows where
        the planner's data are thin (``--planning.value-pessimism`` plans against it).
      seed: command draws, candidate picks and fits.
    """

    worlds: int = 8
    seconds: float = 4.0
    change_s: float = 1.0
    record: int = 16
    holdout: float = 0.25
    rounds: int = 3
    steps: int = 1000
    batch: int = 1024
    learning_rate: float = 3e-4
    discount: float = 0.97
    lam: float = 0.95
    error_model: bool = True
    error_width: int = 64
    ensemble: int = 1
    seed: int = 1

    def __post_init__(self):
        if self.worlds < 2 or self.record < 2:
            raise ValueError(f"worlds={self.worlds} and record={self.record} must be >= 2 (one "
                             f"world is held out; half the records are the best candidates)")
        if not 0 < self.holdout < 1 or self.seconds <= 0 or self.change_s <= 0:
            raise ValueError("holdout must be in (0, 1), seconds and change_s > 0")
        if self.ensemble < 1:
            raise ValueError(f"ensemble={self.ensemble} must be >= 1 (value members)")

    def learned_config(self, width: int = 256) -> learned.LearnedConfig:
        return learned.LearnedConfig(width=width, steps=self.steps, rounds=self.rounds,
                                     batch=self.batch, learning_rate=self.learning_rate,
                                     discount=self.discount, lam=self.lam)


PRESETS = {"tiny": PlannerValueConfig(worlds=2, seconds=0.1, record=2, rounds=1, steps=20,
                                      batch=32, error_width=8),
           "default": PlannerValueConfig()}


class PlannerData(NamedTuple):
    """What the planner visited, per world ``[N, ...]``."""

    closed: learned.Trajectories  # [N, T, ...] the real closed loop
    cand: learned.Trajectories  # [N, T * M, H, ...] recorded candidates, through the model
    up: jax.Array  # [N, T] the robot was up before the step (later steps are left out)
    err_x: jax.Array  # [N, T * (M H + 1), O + A] one-step error inputs (obs, action)
    err_y: jax.Array  # [N, T * (M H + 1)] the model's base-velocity error (m/s)


def transition(planning: planning_lib.Planning, nq: int, sm: sim_model.SimModel,
               q: jax.Array, qd: jax.Array, u: jax.Array, q2: jax.Array, qd2: jax.Array,
               t: jax.Array | int = 0) -> tuple:
    """``(obs, action, reward, next_obs, terminal)`` of one planner step ``x -> x'`` under
    ``u``: the planner's own reward ``-running_cost``, terminal where ``x'`` has fallen."""
    fell = rollout_mjx.fallen(sm, planning_lib.split(q2, nq).q).astype(jnp.float32)
    return (planning.obs(q, qd), planning.reward_action(q, u), -planning.cost(q, qd, u, t),
            planning.obs(q2, qd2), fell)


def make_record(planning: planning_lib.Planning, sm: sim_model.SimModel, true_step: Callable,
                n_record: int, with_error: bool = True) -> Callable:
    """The closed loop's ``record`` hook (:func:`stride_jax.control.episode.run_episode`):
    the real transition, ``n_record`` candidates rolled out again through the model (each step
    with the model's one-step base-velocity error against ``true_step(q, qd, ctrl, key)``, the
    simulator, from the model's own state), and the model's one-step error where the robot
    really is (against the real next state)."""
    nq = sm.mj.nq

    def candidate(q, qd, actions, key):
        def body(carry, inp):
            q, qd = carry
            u, t, k = inp
            k_model, k_true = jax.random.split(k)
            q2, qd2 = planning.dynamics(q, qd, u, k_model)
            err = jnp.zeros(())
            if with_error:
                _, qd2_true = true_step(planning_lib.split(q, nq).q, qd, planning.ctrl(q, u),
                                        k_true)
                err = jnp.linalg.norm(qd2[:3] - qd2_true[:3])
            return (q2, qd2), transition(planning, nq, sm, q, qd, u, q2, qd2, t) + (err,)

        H = actions.shape[0]
        return jax.lax.scan(body, (q, qd), (actions, jnp.arange(H), jax.random.split(key, H)))[1]

    def record(q, qd, u, info, q2, qd2, down, key):
        k_pick, k_roll, k_model = jax.random.split(key, 3)
        K = info.weights.shape[0]
        best = jax.lax.top_k(info.weights, n_record // 2)[1]
        rand = jax.random.choice(k_pick, K, (n_record - n_record // 2,), replace=False)
        picked = info.candidates[jnp.concatenate([best, rand])]
        cand = jax.vmap(candidate, in_axes=(None, None, 0, 0))(
            q, qd, picked, jax.random.split(k_roll, n_record))
        _, qd2_model = planning.dynamics(q, qd, u, k_model)  # the model where the robot is
        err_real = jnp.linalg.norm(qd2_model[:3] - qd2[:3])
        return transition(planning, nq, sm, q, qd, u, q2, qd2), cand, ~down, err_real

    return record


def collect(planning: planning_lib.Planning, planner: mppi.Planner, sm: sim_model.SimModel,
            mx_sim, true_step: Callable, env_cfg: envs.EnvConfig, cfg: PlannerValueConfig,
            key: jax.Array) -> PlannerData:
    """``cfg.worlds`` closed-loop episodes of the planner with random command schedules (every
    ``change_s`` a draw from ``env_cfg.commands``), recording what :func:`make_record` does.
    Pure; jit it."""
    slots = envs.contact_slots(mx_sim)
    n_steps = max(1, int(round(cfg.seconds / sm.robot.ctrl_dt)))
    record = make_record(planning, sm, true_step, cfg.record, cfg.error_model)
    key_cmd, key_run = jax.random.split(key)
    starts, values = envs.command_schedules(env_cfg.commands, key_cmd, cfg.worlds, 8, cfg.change_s)

    def episode(vals, k):
        return episode_lib.run_episode(sm, mx_sim, slots, planning, planner, n_steps, starts,
                                        vals, k, record=record)[1]

    closed, cand, up, err_real = jax.vmap(episode)(values, jax.random.split(key_run,
                                                                           cfg.worlds))
    N, T = up.shape
    obs, act, rew, nxt, term = closed
    closed_tr = learned.Trajectories(obs, act, rew, nxt, term, jnp.zeros((N, T)))
    # [N, T, M, H, ...] -> [N, T * M, H, ...]: one trajectory per recorded candidate
    c_obs, c_act, c_rew, c_nxt, c_term, c_err = (x.reshape((N, T * cfg.record) + x.shape[3:])
                                                 for x in cand)
    cand_tr = learned.Trajectories(c_obs, c_act, c_rew, c_nxt, c_term, jnp.zeros_like(c_rew))
    width = obs.shape[-1] + act.shape[-1]
    err_x = jnp.concatenate([learned.reward_input(c_obs, c_act).reshape(N, -1, width),
                             learned.reward_input(obs, act)], axis=1)
    err_y = jnp.concatenate([c_err.reshape(N, -1), err_real], axis=1)
    return PlannerData(closed_tr, cand_tr, up, err_x, err_y)


def _worlds(data: PlannerData, sel: slice) -> PlannerData:
    return jax.tree.map(lambda x: x[sel], data)


def _indices(up: np.ndarray, record: int, horizon: int) -> tuple[np.ndarray, ...]:
    """Flat indices of the steps taken while up: closed loop ``[N T]``, candidate steps
    ``[N T M H]``, one-step errors ``[N (T M H + T)]`` (the layouts of :class:`PlannerData`)."""
    cand = np.repeat(up, record * horizon, axis=1)
    err = np.concatenate([np.repeat(up, record * horizon, axis=1), up], axis=1)
    return np.flatnonzero(up), np.flatnonzero(cand), np.flatnonzero(err)


def _flat(x):
    return x.reshape((-1,) + x.shape[2:])


def _per_candidate(d: learned.Trajectories) -> learned.Trajectories:
    """``[N, T M, H, ...]`` -> ``[N T M, H, ...]``: one row per candidate trajectory."""
    return jax.tree.map(_flat, d)


def targets(params: dict | list[dict], d: learned.Trajectories, cfg: PlannerValueConfig
            ) -> jax.Array:
    """The value's lambda-return targets ``[N, T]`` of trajectories ``d`` ``[N, T, ...]`` under
    the value ``params`` (each trajectory bootstraps ``V`` of its last next state; a fall ends
    the return), as :func:`stride_jax.control.learned.refit_value` computes them; an ensemble
    bootstraps its mean."""
    v = jax.vmap(jax.vmap(learned.value_fn(params)))
    return jax.vmap(learned.lambda_returns, in_axes=(0, 0, 0, 0, None, None))(
        d.reward, v(d.next_obs), d.terminal, d.reset, cfg.discount, cfg.lam)


def value_report(params: dict | list[dict], data: PlannerData, cfg: PlannerValueConfig
                 ) -> dict:
    """How well a value (an ensemble: its mean) fits its own lambda-returns on the planner's
    data: R^2 and the mean bias ``V - G`` on the closed loop's states and the candidates' states
    (steps while up). For an ensemble also the members' mean spread (std) there, and the
    correlation of the spread with the mean's absolute error: whether the spread marks where
    the value is wrong."""
    i_closed, i_cand, _ = _indices(np.asarray(data.up), cfg.record, data.cand.reward.shape[-1])
    ensemble = isinstance(params, (list, tuple))
    stacked = learned.stack(list(params)) if ensemble else None
    out = {}
    for name, d, idx in (("closed", data.closed, i_closed),
                         ("candidates", _per_candidate(data.cand), i_cand)):
        if ensemble:  # every member once: their mean predicts, their spread is reported
            members = _flat(jax.vmap(jax.vmap(
                lambda o: learned.apply_ensemble(stacked, o)))(d.obs))[idx]  # [n, E]
            pred = jnp.mean(members, axis=-1)
        else:
            pred = _flat(jax.vmap(jax.vmap(learned.value_fn(params)))(d.obs))[idx]
        target = _flat(targets(params, d, cfg))[idx]
        out[f"r2_{name}"] = learned.r2(pred, target)
        out[f"bias_{name}"] = float(jnp.mean(pred - target))
        if ensemble:
            spread = jnp.std(members, axis=-1)
            out[f"spread_{name}"] = float(jnp.mean(spread))
            out[f"spread_error_corr_{name}"] = float(
                jnp.corrcoef(spread, jnp.abs(pred - target))[0, 1])
    return out


def fit(key: jax.Array, cfg: PlannerValueConfig, value_params: dict, data: PlannerData
        ) -> tuple[dict, dict | None, dict]:
    """``(value_params, error_params or None, report)``: the value refitted from
    ``value_params`` on the planner's data of all but the held-out worlds (the first
    ``holdout`` share; a list of ``cfg.ensemble`` members where it is > 1), the one-step error
    model, and their held-out scores."""
    up = np.asarray(data.up)
    N = up.shape[0]
    n_test = max(1, int(round(cfg.holdout * N)))
    if n_test >= N:
        raise ValueError(f"{N} worlds leave none to train on after holding out {n_test}")
    train, test = _worlds(data, slice(n_test, None)), _worlds(data, slice(0, n_test))
    H = data.cand.reward.shape[-1]
    i_closed, i_cand, i_err = _indices(up[n_test:], cfg.record, H)
    if i_closed.size == 0:
        raise ValueError("the planner was down at every training step: no data to fit")
    key_v, key_e = jax.random.split(key)
    lc = cfg.learned_config()
    # the steps to fit are arguments, so that every member of an ensemble shares one compile
    refit = jax.jit(lambda k, p, closed, cand, ic, ia: learned.refit_value(
        k, lc, p, [(closed, ic), (cand, ia)]))
    cand_train = _per_candidate(train.cand)
    new_params, losses = refit(key_v, value_params, train.closed, cand_train, i_closed, i_cand)
    if cfg.ensemble > 1:  # the other members on bootstrap resamples of the training steps
        rng = np.random.default_rng(cfg.seed)
        members = [new_params]
        for e in range(1, cfg.ensemble):
            boot = [np.sort(rng.choice(i, i.size)) for i in (i_closed, i_cand)]
            members.append(refit(jax.random.fold_in(key_v, e), value_params, train.closed,
                                 cand_train, *boot)[0])
        new_params = members
    report = dict(worlds=N, held_out_worlds=n_test, closed_steps=int(i_closed.size),
                  candidate_steps=int(i_cand.size), horizon=H, ensemble=cfg.ensemble,
                  value_loss_last=float(losses[-1, -1]),
                  value_before=value_report(value_params, test, cfg),
                  value_after=value_report(new_params, test, cfg))
    err_params = None
    if cfg.error_model:
        ec = dataclasses.replace(lc, width=cfg.error_width, depth=2)
        x, y = _flat(train.err_x)[i_err], _flat(train.err_y)[i_err]
        err_params, _ = jax.jit(lambda k, x, y: learned.fit_scalar(k, ec, x, y))(key_e, x, y)
        _, _, t_err = _indices(up[:n_test], cfg.record, H)
        xt, yt = _flat(test.err_x)[t_err], _flat(test.err_y)[t_err]
        pred = jax.vmap(lambda xi: learned.apply(err_params, xi))(xt)
        T = up.shape[1]
        along = np.asarray(test.err_y[:, :-T]).reshape(n_test, T, -1)
        real = np.asarray(test.err_y[:, -T:])
        up_t = up[:n_test]
        report["error_model"] = dict(
            r2_held_out=learned.r2(pred, yt),
            mean_error_closed_loop=float(real[up_t].mean()) if up_t.any() else float("nan"),
            mean_error_candidates=float(along[up_t].mean()) if up_t.any() else float("nan"))
    return new_params, err_params, report


def save_error_model(path: pathlib.Path, params: dict) -> None:
    blob = serialization.msgpack_serialize(jax.device_get(params))
    atomic_write(path, lambda f: f.write(blob))


def load_error_model(path: str | pathlib.Path) -> dict:
    """The one-step error model written by :func:`save_error_model`."""
    path = pathlib.Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no one-step error model at {path}")
    return jax.tree.map(jnp.asarray, serialization.msgpack_restore(path.read_bytes()))
