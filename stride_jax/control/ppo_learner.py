"""The PPO learner: Brax's networks, loss, GAE, observation normaliser and unroll, driven by one
jitted epoch of our own (:func:`make_trainer`), its training state (:class:`TrainState`: all a
run needs to continue exactly) and the policy of its parameters (:func:`make_policy`).

Why our own epoch rather than ``brax.training.agents.ppo.train``, and how runs are chunked,
checkpointed and resumed: :mod:`stride_jax.control.ppo`, which runs this module with one of its
named presets of :class:`PPOConfig`.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import optax

from stride_jax.control import wrappers


@dataclasses.dataclass(frozen=True)
class PPOConfig:
    """A PPO run (Brax ``ppo.train`` hyper-parameters plus chunking).

    Attributes:
      robot: ``go1`` or ``g1`` (the environment preset of :mod:`stride_jax.control.envs`).
      out: run folder.
      chunk_steps: env steps per chunk (an upper bound when ``minutes`` is set).
      minutes: wall-clock budget of a chunk, compilation included (0: none).
      checkpoints: checkpoints per chunk (Brax "evals"; each is a sync point).
      total_steps: the run is complete at this many env steps; a further chunk does nothing.
      num_envs, episode_length, unroll_length, batch_size, num_minibatches, num_updates_per_batch,
      learning_rate, entropy_cost, discounting, gae_lambda, clipping_epsilon, max_grad_norm,
      reward_scaling: as in ``brax.training.agents.ppo.train``.
      policy_width, policy_depth, value_width, value_depth: MLP sizes (swish).
      seed: base seed (chunk ``i`` trains with ``seed + i``).
      friction_min, friction_max, action_noise, softness_min, softness_max, tilt_max_deg,
        tilt_min_deg, tilt_heading_deg, tilt_friction_margin, sensor_noise, payload_max,
        payload_body: the environment's domain
        randomisation
        (:data:`stride_jax.control.envs.RANDOMISATION`, the
        :class:`~stride_jax.control.envs.EnvConfig` fields of these names: each episode's ground
        friction factor, noise on the joint targets, each episode's ground softness (contact
        time constant factor), each episode's slope (its range, its uphill direction's spread
        about the start's forward), the slope bounded by what the episode's
        friction holds, the policy's observation through a real robot's sensors scaled by
        ``sensor_noise``, each episode's load up to ``payload_max`` of the robot's mass on
        ``payload_body``); the defaults train
        on the robot's own model on level ground without noise.
      init_from: a PPO run folder whose checkpoint (networks, observation normaliser, optimiser
        state) starts this run, counted from 0 env steps (fine-tuning: a trained walking policy
        made robust under domain randomisation costs a chunk, not a run); read by the first
        chunk only, its networks must match these; "" (default): fresh networks.
    """

    robot: str = "go1"
    out: str = "runs/ppo_go1"
    chunk_steps: int = 100_000_000
    minutes: float = 0.0
    checkpoints: int = 40
    total_steps: int = 200_000_000
    num_envs: int = 8192
    episode_length: int = 1000
    unroll_length: int = 20
    batch_size: int = 256
    num_minibatches: int = 32
    num_updates_per_batch: int = 4
    learning_rate: float = 3e-4
    entropy_cost: float = 1e-2
    discounting: float = 0.97
    gae_lambda: float = 0.95
    clipping_epsilon: float = 0.3
    max_grad_norm: float = 1.0
    reward_scaling: float = 1.0
    policy_width: int = 128
    policy_depth: int = 4
    value_width: int = 256
    value_depth: int = 5
    seed: int = 0
    friction_min: float = 1.0
    friction_max: float = 1.0
    action_noise: float = 0.0
    softness_min: float = 1.0
    softness_max: float = 1.0
    tilt_max_deg: float = 0.0
    tilt_min_deg: float = 0.0
    tilt_heading_deg: float = 180.0
    tilt_friction_margin: float = 0.0
    sensor_noise: float = 0.0
    payload_max: float = 0.0
    payload_body: str = ""
    init_from: str = ""

    @property
    def steps_per_update(self) -> int:
        """Env steps per PPO update (one batch of unrolls)."""
        return self.batch_size * self.unroll_length * self.num_minibatches

    def __post_init__(self):
        problems = []
        if self.batch_size * self.num_minibatches % self.num_envs:
            problems.append(f"batch_size * num_minibatches = "
                            f"{self.batch_size * self.num_minibatches} must be a multiple of "
                            f"num_envs = {self.num_envs}")
        if self.chunk_steps < self.checkpoints * self.steps_per_update:
            problems.append(f"chunk_steps={self.chunk_steps} is below one update "
                            f"({self.steps_per_update} env steps) per checkpoint "
                            f"({self.checkpoints})")
        for name in ("checkpoints", "num_envs", "episode_length", "unroll_length",
                     "policy_depth", "value_depth"):
            if getattr(self, name) < 1:
                problems.append(f"{name} must be >= 1")
        if self.minutes < 0:
            problems.append("minutes must be >= 0")
        if problems:
            raise ValueError("bad PPO config: " + "; ".join(problems))



def network_factory(cfg: PPOConfig) -> Callable:
    from brax.training.agents.ppo import networks as ppo_networks
    return functools.partial(ppo_networks.make_ppo_networks,
                             policy_hidden_layer_sizes=(cfg.policy_width,) * cfg.policy_depth,
                             value_hidden_layer_sizes=(cfg.value_width,) * cfg.value_depth)


def _networks(cfg: PPOConfig, obs_size: int, action_size: int):
    from brax.training.acme import running_statistics
    return network_factory(cfg)((obs_size,), action_size,
                                preprocess_observations_fn=running_statistics.normalize)


def _optimizer(cfg: PPOConfig) -> optax.GradientTransformation:
    return optax.chain(optax.clip_by_global_norm(cfg.max_grad_norm),
                       optax.adam(cfg.learning_rate))


class TrainState(NamedTuple):
    """Everything a chunk needs to continue exactly (a pytree)."""

    normalizer: Any  # brax running_statistics.RunningStatisticsState over observations
    policy: Any  # policy network parameters
    value: Any  # value network parameters
    opt_state: Any  # optax state over (policy, value)
    key: jax.Array  # raw uint32 key data [2]

    @property
    def params(self) -> tuple:
        """``(normaliser, policy, value)``, Brax's inference layout."""
        return (self.normalizer, self.policy, self.value)


def init_state(cfg: PPOConfig, obs_size: int, action_size: int, key: jax.Array) -> TrainState:
    """A fresh training state (also the structure checkpoints restore into)."""
    from brax.training.acme import running_statistics, specs
    from brax.training.agents.ppo import losses as ppo_losses
    nets = _networks(cfg, obs_size, action_size)
    key_policy, key_value, key_train = jax.random.split(key, 3)
    policy = nets.policy_network.init(key_policy)
    value = nets.value_network.init(key_value)
    norm = running_statistics.init_state(specs.Array((obs_size,), jnp.dtype("float32")))
    opt_state = _optimizer(cfg).init(ppo_losses.PPONetworkParams(policy, value))
    return _strong(TrainState(norm, policy, value, opt_state, jax.random.key_data(key_train)))


def _strong(tree):
    """Arrays without weak types (Python scalars in Brax's normaliser state would otherwise make
    the first epoch compile twice: once for the weak inputs, once for the epoch's outputs)."""
    def leaf(x):
        x = jnp.asarray(x)
        return x.astype(x.dtype)
    return jax.tree.map(leaf, tree)


class Trainer(NamedTuple):
    init: Callable  # key -> TrainState
    reset: Callable  # key -> batched, wrapped env state (jitted)
    epoch: Callable  # (TrainState, env_state) -> (TrainState, env_state, metrics) (jitted)
    updates_per_epoch: int


def make_trainer(cfg: PPOConfig, env: Any) -> Trainer:
    """PPO (Brax's loss, networks, normaliser and unroll) for an unwrapped Brax env; one epoch is
    ``updates_per_epoch`` updates of ``cfg.steps_per_update`` env steps, in one jitted scan."""
    from brax.training import acting
    from brax.training.acme import running_statistics
    from brax.training.agents.ppo import losses as ppo_losses
    from brax.training.agents.ppo import networks as ppo_networks

    env_w = wrappers.wrap_for_training(env, cfg.episode_length)
    n_obs, nu = env.observation_size, env.action_size
    nets = _networks(cfg, n_obs, nu)
    make_inference = ppo_networks.make_inference_fn(nets)
    optimizer = _optimizer(cfg)
    loss_fn = functools.partial(
        ppo_losses.compute_ppo_loss, ppo_network=nets, entropy_cost=cfg.entropy_cost,
        discounting=cfg.discounting, reward_scaling=cfg.reward_scaling,
        gae_lambda=cfg.gae_lambda, clipping_epsilon=cfg.clipping_epsilon,
        normalize_advantage=True)
    n_unrolls = cfg.batch_size * cfg.num_minibatches // cfg.num_envs
    extra = ("truncation", "episode_metrics", "episode_done")
    updates = max(1, cfg.chunk_steps // (cfg.checkpoints * cfg.steps_per_update))

    def update(carry, _):
        ts, env_state = carry
        key, k_unroll, k_sgd = jax.random.split(jax.random.wrap_key_data(ts.key), 3)
        policy = make_inference(ts.params)

        def unroll(c, _):
            st, k = c
            k, k_now = jax.random.split(k)
            st, data = acting.generate_unroll(env_w, st, policy, k_now, cfg.unroll_length, extra)
            return (st, k), data

        (env_state, _), data = jax.lax.scan(unroll, (env_state, k_unroll), length=n_unrolls)
        # [n_unrolls, T, envs, ...] -> [n_unrolls * envs, T, ...]
        data = jax.tree.map(lambda x: jnp.swapaxes(x, 1, 2).reshape((-1,) + x.shape[1:2]
                                                                    + x.shape[3:]), data)
        normalizer = running_statistics.update(ts.normalizer, data.observation)

        def sgd(c, _):
            opt_state, params, k = c
            k, k_perm, k_grad = jax.random.split(k, 3)
            shuffled = jax.tree.map(lambda x: jax.random.permutation(k_perm, x).reshape(
                (cfg.num_minibatches, -1) + x.shape[1:]), data)

            def minibatch(c2, batch):
                opt_state, params, k = c2
                k, k_loss = jax.random.split(k)
                (_, metrics), grads = jax.value_and_grad(loss_fn, has_aux=True)(
                    params, normalizer, batch, k_loss)
                upd, opt_state = optimizer.update(grads, opt_state, params)
                return (opt_state, optax.apply_updates(params, upd), k), metrics

            (opt_state, params, _), metrics = jax.lax.scan(minibatch, (opt_state, params,
                                                                       k_grad), shuffled)
            return (opt_state, params, k), metrics

        params = ppo_losses.PPONetworkParams(ts.policy, ts.value)
        (opt_state, params, _), metrics = jax.lax.scan(
            sgd, (ts.opt_state, params, k_sgd), length=cfg.num_updates_per_batch)
        done = data.extras["state_extras"]["episode_done"]
        episodes = data.extras["state_extras"]["episode_metrics"]
        sums = {k: jnp.sum(v * done) for k, v in episodes.items()}
        ts = TrainState(normalizer, params.policy, params.value, opt_state,
                        jax.random.key_data(key))
        return (ts, env_state), (jax.tree.map(jnp.mean, metrics), sums, jnp.sum(done))

    def epoch(ts, env_state):
        (ts, env_state), (losses, sums, n) = jax.lax.scan(update, (ts, env_state),
                                                           length=updates)
        count = jnp.sum(n)
        metrics = {f"train/{k}": jnp.mean(v) for k, v in losses.items()}
        metrics.update({f"episode/{k}": jnp.sum(v) / jnp.maximum(count, 1)
                        for k, v in sums.items()})
        metrics["episode/count"] = count
        return ts, env_state, metrics

    def reset(key):  # Brax's wrappers expect raw uint32 keys [num_envs, 2]
        return env_w.reset(jax.random.key_data(jax.random.split(key, cfg.num_envs)))

    return Trainer(functools.partial(init_state, cfg, n_obs, nu), jax.jit(reset),
                   jax.jit(epoch, donate_argnums=(0, 1)), updates)


def make_policy(cfg: PPOConfig, params: tuple, obs_size: int, action_size: int,
                deterministic: bool = True) -> tuple[Callable, Callable]:
    """``policy(obs, key) -> action`` and ``value(obs) -> []`` of Brax PPO parameters."""
    from brax.training.agents.ppo import networks as ppo_networks
    nets = _networks(cfg, obs_size, action_size)
    inference = ppo_networks.make_inference_fn(nets)(params, deterministic=deterministic)

    def policy(obs, key):
        if obs.shape[-1] != obs_size:
            raise ValueError(f"policy observation must have {obs_size} entries, got {obs.shape}")
        return inference(obs, key)[0]

    def value(obs):
        return nets.value_network.apply(params[0], params[2], obs)

    return policy, value
