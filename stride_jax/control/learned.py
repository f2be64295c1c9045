"""Learned reward and value models for planning (Dreamer-MPC style, the paper's Sec. IV-B).

Both are small Flax MLPs (:func:`stride_jax.dynamics.mlp.mlp`) as pure ``init``/``apply`` pairs
over a params pytree that carries its own input and output normalisation:

* reward ``r(obs, action) -> []``: regression on the environment's rewards;
* value ``V(obs) -> []``: fitted value iteration on lambda-returns,

      G_t = r_t + gamma c_t ((1 - lambda) V(s_{t+1}) + lambda G_{t+1}),   G_T = V(s_T),

  with ``c_t = 0`` where the episode terminated (a fall) and the previous round's ``V`` in the
  targets; each round regresses ``V`` on the new targets.

Both are trained from rollouts of the environment (:func:`rollouts`; a PPO policy or any other),
and turn into MPPI's running cost (``-r``) and terminal value (:func:`planner_terms`).

Fitted from a trained PPO run's rollouts by ``stride fit-reward-value``
(:mod:`stride_jax.jobs.fit_reward_value`), which writes ``reward_value.msgpack`` (:func:`save`,
:func:`load`) and a held-out report.
"""

from __future__ import annotations

import dataclasses
import pathlib
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import serialization

from stride_jax.dynamics import mlp as mlp_lib
from stride_jax.io import atomic_write
from stride_jax.train import loop


@dataclasses.dataclass(frozen=True)
class LearnedConfig:
    """Network size and training of the reward and value models.

    Attributes:
      width, depth: hidden width and layers of each MLP (SiLU).
      steps: SGD steps for the reward model, and per round for the value model.
      rounds: fitted-value-iteration rounds (targets recomputed with the last value model).
      batch: examples per SGD step.
      learning_rate: Adam step size.
      discount: gamma of the value (per control step).
      lam: lambda of the returns.
    """

    width: int = 256
    depth: int = 2
    steps: int = 2000
    rounds: int = 5
    batch: int = 1024
    learning_rate: float = 1e-3
    discount: float = 0.97
    lam: float = 0.95

    def __post_init__(self):
        if not 0 <= self.discount < 1 or not 0 <= self.lam <= 1:
            raise ValueError(f"discount must be in [0, 1) and lam in [0, 1], got "
                             f"{self.discount}, {self.lam}")
        if min(self.width, self.depth, self.steps, self.rounds, self.batch) < 1:
            raise ValueError("width, depth, steps, rounds and batch must be >= 1")


PRESETS = {
    "tiny": LearnedConfig(width=32, depth=2, steps=200, rounds=3, batch=256),
    "default": LearnedConfig(),
}


class Trajectories(NamedTuple):
    """Rollouts, ``[N, T, ...]`` (N worlds, T steps)."""

    obs: jax.Array  # [N, T, O] observation before the action
    action: jax.Array  # [N, T, A]
    reward: jax.Array  # [N, T]
    next_obs: jax.Array  # [N, T, O]
    terminal: jax.Array  # [N, T] 1 where the step ended the episode by failure (no bootstrap)
    reset: jax.Array  # [N, T] 1 where the episode ended (failure or time limit): returns stop


# ---------------------------------------------------------------------------------------------
# Networks with their own normalisation.


def _stats(x: jax.Array) -> tuple[jax.Array, jax.Array]:
    x = x.reshape(-1, x.shape[-1])
    return jnp.mean(x, 0), jnp.std(x, 0) + 1e-3


def init(key: jax.Array, cfg: LearnedConfig, inputs: jax.Array, targets: jax.Array) -> dict:
    """Parameters of a scalar model of ``inputs`` ``[..., D]``; the examples set the input and
    output normalisation."""
    net_init, _ = mlp_lib.mlp(mlp_lib.MLPConfig(cfg.width, cfg.depth), 1)
    x_mean, x_std = _stats(inputs)
    return {"net": net_init(key, inputs.shape[-1]), "x_mean": x_mean, "x_std": x_std,
            "y_mean": jnp.mean(targets), "y_std": jnp.std(targets) + 1e-3}


def apply(params: dict, x: jax.Array) -> jax.Array:
    """The model's output ``[]`` for one input ``[D]`` (vmap for batches)."""
    if x.ndim != 1 or x.shape[0] != params["x_mean"].shape[0]:
        raise ValueError(f"model input must have shape [{params['x_mean'].shape[0]}] (one "
                         f"example; vmap for batches), got {x.shape}")
    width = params["net"]["params"]["Dense_0"]["kernel"].shape[1]
    depth = len(params["net"]["params"]) - 1
    _, net_apply = mlp_lib.mlp(mlp_lib.MLPConfig(width, depth), 1)
    z = net_apply(params["net"], (x - params["x_mean"]) / params["x_std"])[0]
    return z * params["y_std"] + params["y_mean"]


def reward_input(obs: jax.Array, action: jax.Array) -> jax.Array:
    return jnp.concatenate([obs, action], axis=-1)


def _regress(key: jax.Array, cfg: LearnedConfig, params: dict, x: jax.Array, y: jax.Array,
             input_noise: jax.Array | None = None) -> tuple[dict, jax.Array]:
    """``cfg.steps`` Adam steps (constant step size) of mean squared error (normalised targets)
    on ``x [M, D]``, ``y [M]``, as one scan of the training loop
    (:func:`stride_jax.train.loop.scan_steps`; pure: runs inside ``jit`` and the value model's
    rounds); returns the parameters and the loss per step. ``input_noise [D]``: each minibatch's
    inputs take Gaussian noise of this std, in units of each input's normalisation std
    (:func:`check_input_noise`), the targets kept."""
    opt = optax.adam(cfg.learning_rate)
    fixed = {k: v for k, v in params.items() if k != "net"}  # the normalisation is not trained

    def loss(net, batch, key):
        p = {**fixed, "net": net}
        xb = batch["x"]
        if input_noise is not None:
            xb = xb + input_noise * params["x_std"] * jax.random.normal(key, xb.shape, xb.dtype)
        pred = jax.vmap(lambda xi: apply(p, xi))(xb)
        return jnp.mean(((pred - batch["y"]) / params["y_std"]) ** 2), {}

    (net, _), losses, _ = loop.scan_steps(loss, opt, params["net"], opt.init(params["net"]),
                                          {"x": x, "y": y}, key, 0, cfg.steps, cfg.batch)
    return {**params, "net": net}, losses


def _flat(x: jax.Array) -> jax.Array:
    return x.reshape((-1,) + x.shape[2:])


def _check(data: Trajectories) -> None:
    n, t = data.reward.shape[:2] if data.reward.ndim == 2 else (None, None)
    if n is None:
        raise ValueError(f"rewards must be [N, T], got {data.reward.shape}")
    for name in ("obs", "next_obs", "action"):
        a = getattr(data, name)
        if a.ndim != 3 or a.shape[:2] != (n, t):
            raise ValueError(f"{name} must be [N={n}, T={t}, dim], got {a.shape}")
    for name in ("terminal", "reset"):
        if getattr(data, name).shape != (n, t):
            raise ValueError(f"{name} must be [N={n}, T={t}], got {getattr(data, name).shape}")


def fit_scalar(key: jax.Array, cfg: LearnedConfig, x: jax.Array, y: jax.Array
               ) -> tuple[dict, jax.Array]:
    """A scalar model of examples ``x [M, D]``, ``y [M]`` (its normalisation from them);
    returns its parameters and training losses."""
    key_init, key_fit = jax.random.split(key)
    return _regress(key_fit, cfg, init(key_init, cfg, x, y), x, y)


def fit_reward(key: jax.Array, cfg: LearnedConfig, data: Trajectories) -> tuple[dict, jax.Array]:
    """A reward model of ``data``; returns its parameters and training losses."""
    _check(data)
    return fit_scalar(key, cfg, _flat(reward_input(data.obs, data.action)), _flat(data.reward))


def check_relabel(env_cfg, share: float, std: float) -> None:
    """Raises where :func:`relabel_commands` cannot relabel ``env_cfg``'s rollouts at ``share``
    and ``std`` (a caller checks before it rolls them out)."""
    if not 0.0 <= share <= 1.0 or std < 0:
        raise ValueError(f"relabel: share={share} must be in [0, 1] and std={std} >= 0")
    if env_cfg.sensor_noise:
        raise ValueError(f"relabel: the task observes through sensors (sensor_noise="
                         f"{env_cfg.sensor_noise}): its observed velocities are not the ones "
                         "its reward read, so the tracking terms cannot be recomputed from them")


def relabel_commands(data: Trajectories, env_cfg, dt: float, key: jax.Array, share: float,
                     std: float) -> Trajectories:
    """``data`` with the command of a ``share`` of its worlds moved, and their rewards' tracking
    terms recomputed for it (hindsight relabelling).

    Why: rolled out by a policy, the velocity is always near the command, so a reward fitted on
    those rollouts never sees a velocity off its command and extrapolates: G1's learned reward
    kept rising past the command (``results/planning_diagnosis/g1_reward_shape_walk.md``) and its
    planner, free to ask the policy for more (the policy family), walked faster than asked
    under slow commands (``results/select_learned_g1_gpu/session96/``). The tracking terms are
    known functions of the command and the next state's base velocity (both in the
    observations: :func:`stride_jax.control.envs.observe`), so the same steps under another
    command have a known reward.

    Each chosen world's command moves by one offset ``N(0, std * range)`` per component
    (``range``: the largest magnitude of the component's training range), held over the
    rollout; commands that stop (``|command| <= 0.1``, where the stand-still and air-time terms
    switch) and commands the offset would make stop keep their value, so the terms that read
    only whether it moves are unchanged. The reward's tracking part changes by ``dt *
    (scale_lin (k_lin(c', v') - k_lin(c, v')) + scale_ang (k_ang(c', w') - k_ang(c, w')))``
    with ``v', w'`` the next observation's base velocities (exact only where the task observes
    the state itself: a task with sensor noise is refused); the environment clips the total at
    0, so a step whose reward was clipped keeps 0 (its unclipped value is unknown).
    """
    from stride_jax.control import envs  # the velocity task's layout and reward terms

    _check(data)
    check_relabel(env_cfg, share, std)
    o = data.obs.shape[-1]
    at = envs.obs_layout_of_size(env_cfg, o, "relabel")
    lo, hi = env_cfg.commands.bounds()
    scale = jnp.maximum(jnp.abs(lo), jnp.abs(hi))
    k_pick, k_off = jax.random.split(key)
    n = data.obs.shape[0]
    picked = jax.random.bernoulli(k_pick, share, (n,))
    offset = std * scale * jax.random.normal(k_off, (n, 3)) * picked[:, None]

    def moved(c):  # [N, T, 3]: moving commands that stay moving take the offset
        c2 = c + offset[:, None, :]
        keep = ((jnp.linalg.norm(c, axis=-1) <= envs.MOVING)
                | (jnp.linalg.norm(c2, axis=-1) <= envs.MOVING))
        return jnp.where(keep[..., None], c, c2)

    c_old = data.obs[..., at["command"]]
    c_new = moved(c_old)
    v, w = data.next_obs[..., at["v"]], data.next_obs[..., at["w"]]

    def tracking(c):  # the tracking part of the reward, scaled, per period
        terms = envs.tracking_terms(env_cfg, c, v, w)
        return dt * sum(getattr(env_cfg.rewards, k) * x for k, x in terms.items())
    change = tracking(c_new) - tracking(c_old)
    reward = jnp.where(data.reward > 0, jnp.maximum(data.reward + change, 0.0), data.reward)
    return data._replace(
        obs=data.obs.at[..., at["command"]].set(c_new),
        next_obs=data.next_obs.at[..., at["command"]].set(moved(data.next_obs[..., at["command"]])),
        reward=reward)


def lambda_returns(reward: jax.Array, next_value: jax.Array, terminal: jax.Array,
                   reset: jax.Array, discount: float, lam: float) -> jax.Array:
    """Lambda-returns ``[T]`` of one trajectory: ``reward``, ``next_value`` (V of the next
    observation), ``terminal`` (no bootstrap) and ``reset`` (the return stops) are ``[T]``."""
    def body(g_next, inp):
        r, v, term, done = inp
        cont = 1.0 - term
        g_next = jnp.where(done > 0, v, g_next)  # a new episode follows: bootstrap only
        g = r + discount * cont * ((1 - lam) * v + lam * g_next)
        return g, g

    _, g = jax.lax.scan(body, next_value[-1], (reward, next_value, terminal, reset),
                        reverse=True)
    return g


def check_input_noise(input_noise: Any, size: int) -> None:
    """Refuses an input-noise vector that is not ``[size]``, finite and >= 0 (concrete arrays
    only: under ``jit`` the shape alone is checked)."""
    shape = getattr(input_noise, "shape", None)
    if shape != (size,):
        raise ValueError(f"input_noise must have shape [{size}] (one std per input), got {shape}")
    if not isinstance(input_noise, jax.core.Tracer):
        a = np.asarray(input_noise)
        if not np.all(np.isfinite(a)) or np.any(a < 0):
            raise ValueError(f"input_noise must be finite and >= 0, got {a}")


def fit_value(key: jax.Array, cfg: LearnedConfig, data: Trajectories,
              input_noise: jax.Array | None = None) -> tuple[dict, jax.Array]:
    """A value model of ``data`` by ``cfg.rounds`` rounds of fitted value iteration; returns its
    parameters and the training losses ``[rounds, steps]``.

    ``input_noise [O]``: the std of Gaussian noise added to each observation input in training,
    in units of that input's spread over ``data`` (0: none), the targets kept: the model is
    smoothed over that distance along each noised input (about a penalty on its slope there),
    so that a planner cannot buy value by moving an input where the policy's states never went
    (G1's planner moved the joint posture so, session 98).
    """
    _check(data)
    if input_noise is not None:
        check_input_noise(input_noise, data.obs.shape[-1])
    x = _flat(data.obs)
    scale = jnp.std(data.reward) / (1 - cfg.discount) + 1e-3
    mean0 = jnp.mean(data.reward) / (1 - cfg.discount)
    key_init, key_fit = jax.random.split(key)
    params = init(key_init, cfg, x, jnp.zeros(1))
    params = {**params, "y_mean": mean0, "y_std": scale}
    returns = jax.vmap(lambda_returns, in_axes=(0, 0, 0, 0, None, None))

    def round_(params, k):
        v_next = jax.vmap(jax.vmap(lambda o: apply(params, o)))(data.next_obs)
        targets = returns(data.reward, v_next, data.terminal, data.reset, cfg.discount, cfg.lam)
        params, losses = _regress(k, cfg, params, x, _flat(targets), input_noise)
        return params, losses

    return jax.lax.scan(round_, params, jax.random.split(key_fit, cfg.rounds))


def refit_value(key: jax.Array, cfg: LearnedConfig, params: dict,
                sets: list[tuple[Trajectories, jax.Array]]) -> tuple[dict, jax.Array]:
    """``cfg.rounds`` rounds of fitted value iteration from ``params`` (kept normalisation) on
    the union of ``sets``: each a :class:`Trajectories` ``[N, T, ...]`` and the indices of its
    flattened ``N * T`` steps to use (a numpy array: steps after a fall left out). Each round's
    targets are the lambda-returns under the previous round's value (bootstrapped at each
    trajectory's end). Returns the parameters and the losses ``[rounds, steps]``."""
    for data, _ in sets:
        _check(data)
    x = jnp.concatenate([_flat(d.obs)[idx] for d, idx in sets])
    returns = jax.vmap(lambda_returns, in_axes=(0, 0, 0, 0, None, None))

    def round_(params, k):
        y = []
        for d, idx in sets:
            v_next = jax.vmap(jax.vmap(lambda o: apply(params, o)))(d.next_obs)
            g = returns(d.reward, v_next, d.terminal, d.reset, cfg.discount, cfg.lam)
            y.append(_flat(g)[idx])
        return _regress(k, cfg, params, x, jnp.concatenate(y))

    return jax.lax.scan(round_, params, jax.random.split(key, cfg.rounds))


# ---------------------------------------------------------------------------------------------
# Data and planning.


def rollouts(env: Any, policy: Callable, key: jax.Array, n_envs: int, n_steps: int,
             episode_length: int = 1000) -> Trajectories:
    """``n_steps`` steps of ``n_envs`` worlds of a Brax env under ``policy(obs, key) -> action``
    (worlds reset freshly when an episode ends). Jit the caller or pass through ``jax.jit``."""
    from stride_jax.control import wrappers
    wrapped = wrappers.wrap_for_training(env, episode_length)
    key_reset, key_run = jax.random.split(key)

    def body(state, k):
        a = jax.vmap(policy)(state.obs, jax.random.split(k, n_envs))
        nxt = wrapped.step(state, a)
        trunc = nxt.info["truncation"]
        # The observation the step reached (an auto-reset swaps in the next episode's first).
        reached = nxt.info["last_obs"]
        return nxt, Trajectories(state.obs, a, nxt.reward, reached, nxt.done * (1 - trunc),
                                 nxt.done)

    state = wrapped.reset(jax.random.key_data(jax.random.split(key_reset, n_envs)))
    _, data = jax.lax.scan(body, state, jax.random.split(key_run, n_steps))
    return jax.tree.map(lambda x: jnp.swapaxes(x, 0, 1), data)


def stack(members: list[dict]) -> dict:
    """Models of the same shape as one pytree with a leading member axis (for
    :func:`apply_ensemble`)."""
    return jax.tree.map(lambda *a: jnp.stack(a), *members)


def apply_ensemble(stacked: dict, x: jax.Array) -> jax.Array:
    """``[E]`` the outputs of an ensemble's members (:func:`stack`) for one input ``[D]``."""
    return jax.vmap(apply, in_axes=(0, None))(stacked, x)


def pessimistic(values: jax.Array, pessimism: float) -> jax.Array:
    """The members' mean minus ``pessimism`` standard deviations (``values [E]``)."""
    return jnp.mean(values) - pessimism * jnp.std(values)


def value_fn(value_params: dict | list[dict], pessimism: float = 0.0) -> Callable:
    """``obs -> V`` of one value model, or of an ensemble (a list of members, :func:`load`
    ``ensemble=True``): :func:`pessimistic` over its members (their mean at 0)."""
    if not isinstance(value_params, (list, tuple)):
        return lambda obs: apply(value_params, obs)
    stacked = stack(list(value_params))
    return lambda obs: pessimistic(apply_ensemble(stacked, obs), pessimism)


def reward_fn(reward_params: dict | list[dict]) -> Callable:
    """``(obs, action) -> r`` of one reward model, or the mean of an ensemble's members (a list,
    :func:`load` ``ensemble=True``; ``stride fit-reward-value --members``)."""
    if not isinstance(reward_params, (list, tuple)):
        return lambda obs, a: apply(reward_params, reward_input(obs, a))
    stacked = stack(list(reward_params))
    return lambda obs, a: jnp.mean(apply_ensemble(stacked, reward_input(obs, a)))


def planner_terms(reward_params: dict | list[dict], value_params: dict | list[dict],
                  obs_of: Callable, value_weight: float = 1.0, pessimism: float = 0.0
                  ) -> tuple[Callable, Callable]:
    """MPPI's ``running_cost(q, qd, u, t) = -r(obs, u)`` and ``terminal_value(q, qd) = w V(obs)``
    for an ``obs_of(q, qd) -> obs`` (the planner's state may carry the command); ``r`` is
    :func:`reward_fn` (the members' mean over an ensemble), ``V`` :func:`value_fn`
    (pessimistic over an ensemble's members)."""
    reward = reward_fn(reward_params)
    value = value_fn(value_params, pessimism)

    def running_cost(q, qd, u, t):
        return -reward(obs_of(q, qd), u)

    def terminal_value(q, qd):
        return value_weight * value(obs_of(q, qd))

    return running_cost, terminal_value


def r2(pred: jax.Array, target: jax.Array) -> float:
    """Coefficient of determination (1: perfect, 0: no better than the mean)."""
    return float(1 - jnp.mean((pred - target) ** 2) / jnp.maximum(jnp.var(target), 1e-12))


def save(path: pathlib.Path, reward_params: dict | list[dict],
         value_params: dict | list[dict]) -> None:
    """Writes the reward and the value; either may be a list, an ensemble, whose first member
    is also stored as the plain model, so that readers of one model keep working."""
    d = {}
    for name, params in (("reward", reward_params), ("value", value_params)):
        members = list(params) if isinstance(params, (list, tuple)) else None
        d[name] = members[0] if members else params
        if members:
            d[f"{name}_ensemble"] = {str(i): m for i, m in enumerate(members)}
    blob = serialization.msgpack_serialize(jax.device_get(d))
    atomic_write(path, lambda f: f.write(blob))


def load(path: str | pathlib.Path, ensemble: bool = False
         ) -> tuple[dict | list[dict], dict | list[dict]]:
    """``(reward_params, value_params)`` written by :func:`save`; with ``ensemble`` each is the
    list of an ensemble's members where the file has one (one model otherwise)."""
    path = pathlib.Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no learned reward/value models at {path}")
    d = serialization.msgpack_restore(path.read_bytes())
    as_jnp = lambda t: jax.tree.map(jnp.asarray, t)

    def read(name):
        members = d.get(f"{name}_ensemble") if ensemble else None
        if members:
            return [as_jnp(members[str(i)]) for i in range(len(members))]
        return as_jnp(d[name])

    return read("reward"), read("value")
