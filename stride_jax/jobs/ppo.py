"""``stride ppo``: one resumable chunk of a PPO warm-start policy into a run folder.

The algorithm, configuration, chunks and checkpoints are the library's
(:mod:`stride_jax.control.ppo`); this job writes the run folder: ``config.json`` (the
:class:`~stride_jax.control.ppo.PPOConfig` and the environment config, checked on every later
chunk), ``checkpoint.msgpack`` after every checkpoint and one ``progress.jsonl`` line each.
Resumes when ``--out`` holds a checkpoint:

    stride ppo --robot go1 --preset gpu --out runs/ppo_go1 --minutes 8
    python -m stride_jax.jobs.ppo --robot go1 --preset gpu --out runs/ppo_go1 --minutes 8
"""

from __future__ import annotations

import dataclasses
import json
import pathlib
import time

import jax

import stride_jax
from stride_jax import config
from stride_jax.control import envs
from stride_jax.control.ppo import (PRESETS, PPOConfig, RunState, load,  # noqa: F401
                                    read_config, save, train_chunk)
from stride_jax.io import atomic_write_text, code_version


def _write_config(out: pathlib.Path, cfg: PPOConfig, env_cfg: envs.EnvConfig) -> None:
    """Writes ``config.json`` on the first chunk; later chunks must match its networks."""
    path = out / "config.json"
    mine = {"ppo": dataclasses.asdict(cfg), "env": dataclasses.asdict(env_cfg)}
    if not path.is_file():
        atomic_write_text(path, json.dumps(mine, indent=1))
        return
    # the run's configs as they read back (fields added since take their defaults)
    old_cfg, old_env = read_config(out)
    fixed = ("robot", "policy_width", "policy_depth", "value_width", "value_depth")
    diff = [k for k in fixed if getattr(old_cfg, k) != mine["ppo"][k]]
    if diff or dataclasses.asdict(old_env) != dataclasses.asdict(env_cfg):
        raise ValueError(f"{out} was started with another robot, network or environment "
                         f"({', '.join(diff) or 'env'}); use a new --out")


def run(cfg: PPOConfig, env_cfg: envs.EnvConfig | None = None, log=print) -> RunState:
    """One chunk into ``cfg.out``: resumes from its checkpoint, saves at every checkpoint."""
    t0 = time.monotonic()
    deadline = t0 + 60 * cfg.minutes if cfg.minutes else None
    env_cfg = env_cfg or envs.config(cfg.robot,
                                     **{k: getattr(cfg, k) for k in envs.RANDOMISATION})
    if env_cfg.robot != cfg.robot:
        raise ValueError(f"environment robot {env_cfg.robot!r} != PPO robot {cfg.robot!r}")
    out = pathlib.Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    _write_config(out, cfg, env_cfg)
    env = envs.VelocityEnv(env_cfg)
    restore = load(out, cfg, env.observation_size, env.action_size)
    if restore is None and cfg.init_from:
        start = pathlib.Path(cfg.init_from)
        if not (start / "checkpoint.msgpack").is_file():
            raise FileNotFoundError(f"--init-from {start}: no checkpoint.msgpack there (a PPO run "
                                    "folder, as `stride ppo --out` writes)")
        first = load(start, cfg, env.observation_size, env.action_size)
        restore = RunState(first.train, 0, 0)
        log(f"{out}: starting from {start}'s networks ({first.env_steps} env steps trained there)")
    if restore and restore.env_steps >= cfg.total_steps:
        log(f"{out}: complete ({restore.env_steps} >= total_steps {cfg.total_steps} env steps)")
        return restore
    log(f"{out}: chunk {restore.chunks + 1 if restore else 1}, from "
        f"{restore.env_steps if restore else 0} env steps, {jax.default_backend()}")

    code = code_version()

    def checkpoint(state, metrics):
        save(out, state)
        line = json.dumps({"env_steps": state.env_steps, "chunk": state.chunks,
                           "wall_s": time.monotonic() - t0, "code": code, **metrics})
        with open(out / "progress.jsonl", "a") as f:
            f.write(line + "\n")
        log(f"  {state.env_steps} env steps ({time.monotonic() - t0:.0f} s, "
            f"{metrics['sps']:.0f} steps/s): episode reward "
            f"{metrics.get('episode/sum_reward', float('nan')):.3f} over "
            f"{metrics.get('episode/count', 0):.0f} episodes, length "
            f"{metrics.get('episode/length', float('nan')):.0f}; checkpoint saved")

    state = train_chunk(cfg, env, restore, checkpoint, deadline)
    log(f"{out}: {state.env_steps} env steps after {state.chunks} chunks "
        f"({time.monotonic() - t0:.0f} s this chunk)")
    return state


def main(argv: list[str] | None = None) -> None:
    def run_chunk(cfg, command, log):
        log(f"command: {command}")
        run(cfg, log=log)

    config.config_main("python -m stride_jax.jobs.ppo", PPOConfig, PRESETS, run_chunk, argv,
                       __doc__.split("\n")[0])


if __name__ == "__main__":
    stride_jax.set_xla_flags()  # before JAX starts: small CPUs deadlock without
    main()
