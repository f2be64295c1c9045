"""``stride fit-reward-value``: the learned reward and value models fitted on rollouts of a
trained PPO run's policy (:mod:`stride_jax.control.learned`), with a held-out report.

Writes ``reward_value.msgpack`` (:func:`stride_jax.control.learned.load` reads it; the closed
loop's ``--learned``) and ``report.json`` to ``--out``:

    stride fit-reward-value --policy runs/ppo_go1 --out runs/learned_go1 --envs 1024 --steps 400
    python -m stride_jax.jobs.fit_reward_value --policy runs/ppo_go1 --out runs/learned_go1
"""

from __future__ import annotations

import dataclasses
import json
import pathlib
import time
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np

import stride_jax
from stride_jax import config
from stride_jax.control import envs as envs_lib, learned as learned_lib, ppo
from stride_jax.io import atomic_write_text, code_version


@dataclasses.dataclass(frozen=True)
class FitConfig:
    """Rollouts of a PPO run's policy, then both models.

    Attributes:
      policy: PPO run folder.
      out: folder for ``reward_value.msgpack`` and ``report.json``.
      envs: worlds rolled out side by side.
      rollout_steps: control steps per world.
      holdout: fraction of the worlds held out for the report.
      seed: rollouts' and fits' key.
      members: reward and value models fitted on the same rollouts, each from its own key
        (member 0 from the key a single fit uses), saved as ensembles: the planner takes the
        members' mean reward and value. Measured (session 93): two single fits of one policy's
        models (seeds 0 and 1: other rollouts, other keys) moved the CPU planner's tracking on
        rough ground by 0.010 m/s, and the one with the higher held-out R^2 planned worse; four
        members on the worse one's rollouts took back most of that on rough ground and pushes,
        little elsewhere (``results/closed_loop/g1_uphill_cpu/``): an ensemble evens out the
        fits' keys, not their rollouts.
      keep_action_noise: roll out with the run's training noise on the joint targets
        (``stride ppo --action-noise``). Off (the default): without it, since the reward model
        takes the applied action as its input and under that noise the environment applied
        another (nor does the planner add any). The run's other randomisation (each episode's
        friction, slope) is kept: it is the variety of states the planner meets, and the value
        under it is the policy's.
      relabel_share: the share of the training worlds whose command is moved after the
        rollout, their rewards' tracking terms recomputed for it
        (:func:`~stride_jax.control.learned.relabel_commands`: a reward fitted on the policy's
        own rollouts never sees a velocity off its command). 0: off (every fit before it). The
        held-out worlds keep their commands: the report's R^2 reads the policy's own steps.
      relabel_std: the offsets' std, as a share of each command component's range.
      relabel_models: which models train on the relabelled worlds: ``both`` (the default), or
        only the ``value`` (the reward then fits the policy's own steps: the value is where
        G1's planner's pull to speed was measured, session 97) or only the ``reward``.
      value_noise: std of the Gaussian noise on the value model's inputs named in
        ``value_noise_parts``, in units of each input's spread over the rollouts (0: off, every
        fit before it; :func:`~stride_jax.control.learned.fit_value`). Why: G1's planner bought
        the value's score by moving the joint posture where the policy's states never went
        (``experiments/plan_bias.py``'s swap table, session 98).
        Measured on G1 (session 99, CPU): one spread on the joint positions and velocities
        brought the planner at full value weight level with the policy on the validation
        episodes (the plain refit 0.017 m/s behind), the joint positions alone part of the way,
        two spreads less well; on Go1 it changed nothing; at 1 m/s it gives back the planner's
        gain on the scenarios (``results/select_learned_g1_cpu/README.md``, "Session 99").
      value_noise_parts: comma-separated parts of the observation
        (:func:`stride_jax.control.envs.obs_layout`: ``v``, ``w``, ``gravity``, ``joint_pos``,
        ``joint_vel``, ``command``, ``clock``) that take it; the default, the joints, is the
        measured one.
      learned: the models' sizes and training
        (:class:`~stride_jax.control.learned.LearnedConfig`: ``--learned.width``,
        ``--learned.steps`` ...; the older flat ``--width``, ``--steps`` ... still answer).
    """

    policy: str = "runs/ppo_go1"
    out: str = "runs/learned_go1"
    envs: int = 1024
    rollout_steps: int = 400
    holdout: float = 0.1
    seed: int = 0
    members: int = 1
    keep_action_noise: bool = False
    relabel_share: float = 0.0
    relabel_std: float = 0.3
    relabel_models: str = "both"
    value_noise: float = 0.0
    value_noise_parts: str = "joint_pos,joint_vel"
    learned: learned_lib.LearnedConfig = learned_lib.LearnedConfig()

    # The flat flags of earlier commands still answer.
    FLAG_ALIASES: ClassVar[dict[str, str]] = {
        f"learned.{f.name}": "--" + f.name.replace("_", "-")
        for f in dataclasses.fields(learned_lib.LearnedConfig)}


RELABEL_MODELS = ("both", "value", "reward")

FIT_PRESETS = {
    "tiny": FitConfig(envs=8, rollout_steps=40, holdout=0.25,
                      learned=learned_lib.PRESETS["tiny"]),
    "default": FitConfig(),
}


def value_input_noise(env_cfg, obs_size: int, std: float, parts: str) -> jax.Array | None:
    """The value's ``input_noise [obs_size]`` (:func:`~stride_jax.control.learned.fit_value`):
    ``std`` on the observation's ``parts`` (comma-separated names of
    :func:`~stride_jax.control.envs.obs_layout`), 0 elsewhere; None where ``std`` is 0."""
    if not std:
        return None
    if std < 0 or not np.isfinite(std):
        raise ValueError(f"value_noise must be finite and >= 0, got {std}")
    layout = envs_lib.obs_layout_of_size(env_cfg, obs_size, "value_noise")
    names = [n.strip() for n in parts.split(",") if n.strip()]
    unknown = [n for n in names if n not in layout]
    if not names or unknown:
        raise ValueError(f"value_noise_parts: unknown part(s) {unknown or parts!r}; the "
                         f"observation's parts are {', '.join(layout)}")
    noise = np.zeros(obs_size, np.float32)
    for n in names:
        noise[layout[n]] = std
    return jnp.asarray(noise)


def _held_out(reward_params, value_params, test, lc) -> dict:
    """Held-out R^2 of a reward and a value model, or of ensembles (lists: the members' mean),
    the value against its own lambda-returns."""
    r_pred = jax.vmap(jax.vmap(learned_lib.reward_fn(reward_params)))(test.obs, test.action)
    v_obs = jax.vmap(jax.vmap(learned_lib.value_fn(value_params)))
    g = jax.vmap(learned_lib.lambda_returns, in_axes=(0, 0, 0, 0, None, None))(
        test.reward, v_obs(test.next_obs), test.terminal, test.reset, lc.discount, lc.lam)
    return {"reward_r2_held_out": learned_lib.r2(r_pred, test.reward),
            "value_r2_held_out": learned_lib.r2(v_obs(test.obs), g)}


def _fit_members(cfg: FitConfig, key_r: jax.Array, key_v: jax.Array, train_r, train_v, test,
                 value_noise: jax.Array | None = None) -> tuple[list, list, dict]:
    """``cfg.members`` reward models on ``train_r`` and value models on ``train_v`` (member
    ``i > 0`` from its own fold of the two keys), the held-out R^2 of the members' mean and, for
    several, of each member."""
    lc = cfg.learned
    fit_r = jax.jit(lambda k, d: learned_lib.fit_reward(k, lc, d))
    fit_v = jax.jit(lambda k, d: learned_lib.fit_value(k, lc, d, value_noise))
    rewards, values, r_losses, v_losses = [], [], [], []
    for i in range(cfg.members):
        kr, kv = (key_r, key_v) if i == 0 else (jax.random.fold_in(key_r, i),
                                                 jax.random.fold_in(key_v, i))
        r_params, r_loss = fit_r(kr, train_r)
        v_params, v_loss = fit_v(kv, train_v)
        rewards.append(r_params)
        values.append(v_params)
        r_losses.append(float(r_loss[-1]))
        v_losses.append(float(v_loss[-1, -1]))
    stats = {**_held_out(rewards, values, test, lc),
             "reward_loss_last": sum(r_losses) / len(r_losses),
             "value_loss_last": sum(v_losses) / len(v_losses)}
    if cfg.members > 1:
        stats["members"] = [_held_out(r, v, test, lc) for r, v in zip(rewards, values)]
    return rewards, values, stats


def fit_from_policy(cfg: FitConfig, command: str = "", log=print) -> dict:
    """Collects rollouts with the (stochastic) PPO policy, fits both models, writes them with a
    held-out report."""
    if cfg.members < 1:
        raise ValueError(f"members must be >= 1, got {cfg.members}")
    if cfg.relabel_models not in RELABEL_MODELS:
        raise ValueError(f"relabel_models must be one of {', '.join(RELABEL_MODELS)}, got "
                         f"{cfg.relabel_models!r}")
    if cfg.relabel_models != "both" and not cfg.relabel_share:
        raise ValueError(f"relabel_models={cfg.relabel_models!r} names what the relabelled "
                         "worlds train, but relabel_share is 0: no world is relabelled")
    t0 = time.monotonic()
    policy, _, env_cfg = ppo.load_policy(cfg.policy, deterministic=False)
    if not cfg.keep_action_noise:
        env_cfg = dataclasses.replace(env_cfg, action_noise=0.0)
    if cfg.relabel_share or cfg.relabel_std < 0:  # what relabel_commands would refuse, first
        learned_lib.check_relabel(env_cfg, cfg.relabel_share, cfg.relabel_std)
    env = envs_lib.VelocityEnv(env_cfg)
    value_noise = value_input_noise(env_cfg, env.observation_size, cfg.value_noise,
                                    cfg.value_noise_parts)  # (bad flags refused before rollouts)
    key_roll, key_r, key_v = jax.random.split(jax.random.key(cfg.seed), 3)
    data = jax.jit(lambda k: learned_lib.rollouts(env, policy, k, cfg.envs, cfg.rollout_steps))(
        key_roll)
    n_test = max(1, int(round(cfg.holdout * cfg.envs)))
    train = jax.tree.map(lambda x: x[n_test:], data)
    test = jax.tree.map(lambda x: x[:n_test], data)
    train_r = train_v = train
    if cfg.relabel_share:  # (its own key: the rollouts and fits keep theirs)
        moved = learned_lib.relabel_commands(train, env_cfg, env.dt,
                                             jax.random.fold_in(jax.random.key(cfg.seed), 7),
                                             cfg.relabel_share, cfg.relabel_std)
        train_r = moved if cfg.relabel_models in ("both", "reward") else train
        train_v = moved if cfg.relabel_models in ("both", "value") else train
    log(f"{cfg.envs} x {cfg.rollout_steps} steps of {env_cfg.robot} ({time.monotonic() - t0:.0f}"
        f" s); mean reward {float(data.reward.mean()):.4f}, falls {float(data.terminal.sum())}")
    rewards, values, stats = _fit_members(cfg, key_r, key_v, train_r, train_v, test, value_noise)
    report = {"command": command, "code": code_version(), "robot": env_cfg.robot,
              "envs": cfg.envs,
              "rollout_steps": cfg.rollout_steps, "held_out_worlds": n_test, **stats,
              "seconds": time.monotonic() - t0, "config": dataclasses.asdict(cfg)}
    out = pathlib.Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    one = cfg.members == 1
    learned_lib.save(out / "reward_value.msgpack", rewards[0] if one else rewards,
                     values[0] if one else values)
    atomic_write_text(out / "report.json", json.dumps(report, indent=1))
    log(f"reward R^2 (held out) {report['reward_r2_held_out']:.3f}, value R^2 against its "
        f"lambda-returns {report['value_r2_held_out']:.3f}; wrote {out}")
    return report


def main(argv: list[str] | None = None) -> None:
    config.config_main("python -m stride_jax.jobs.fit_reward_value", FitConfig, FIT_PRESETS,
                       fit_from_policy, argv, __doc__.split("\n")[0])


if __name__ == "__main__":
    stride_jax.set_xla_flags()  # before JAX starts: small CPUs deadlock without
    main()
