"""The ``stride`` command. Each subcommand is a job whose flags are derived from its config
dataclass (:mod:`stride_jax.config`); the jobs live in :mod:`stride_jax.jobs`, apart from the
library they apply.

    stride data --robot go1 [--preset tiny|default|paper] [--episodes 64 ...]
    stride train --robot pendulum --model stride [--preset tiny|default|paper] [--steps ...]
    stride eval --runs 'runs/go1/*' [--preset tiny|default] [--horizon 30 ...]
    stride bench-sim [--preset tiny|default|gpu] [--robots go1,g1 ...]
    stride bench-mppi [--preset tiny|target|default] [--samples 64,256 --horizons 10,20 ...]
    stride ppo --robot go1 --preset gpu --out runs/ppo_go1 --minutes 8   (one resumable chunk)
    stride fit-reward-value --policy runs/ppo_go1 --out runs/learned_go1
    stride closed-loop --preset tiny [--models oracle,nominal,stride=RUN ...]
    stride select-learned --policy runs/ppo_go1 --candidates a=FILE,b=FILE [--model NAME=RUN]
    stride show [--stride runs/pendulum/stride --baseline runs/pendulum/delan --phase.grid 15]
    stride gap diagnose --robot go1 --logs DIR --out DIR   (also: gap simulate, import, export, bench)
"""

from __future__ import annotations

import argparse
import shlex
import sys

import stride_jax
from stride_jax import config


# name -> (job module, config class, presets, help, run): a job's module is imported only when
# its subcommand runs or shows its flags (`stride --help` imported all of them: 8 s on 2 cores)
COMMANDS = {
    "data": ("data", "DataConfig", "PRESETS", "generate a dataset", "run"),
    "train": ("train", "TrainConfig", "PRESETS", "train a dynamics model", "run"),
    "eval": ("eval", "EvalConfig", "PRESETS", "Table I metrics of trained runs", "run"),
    "bench-sim": ("bench_sim", "BenchConfig", "PRESETS", "simulation throughput", "run"),
    "bench-mppi": ("bench_mppi", "BenchConfig", "PRESETS", "MPPI step latency", "run"),
    "ppo": ("ppo", "PPOConfig", "PRESETS", "one PPO chunk of a warm-start policy (resumes)",
            "run"),
    "fit-reward-value": ("fit_reward_value", "FitConfig", "FIT_PRESETS",
                         "learned reward and value models from a PPO run", "fit_from_policy"),
    "closed-loop": ("closed_loop", "ClosedLoopConfig", "PRESETS",
                    "closed-loop MPPI in MJX per model and scenario", "run"),
    "select-learned": ("select_learned", "SelectConfig", "PRESETS",
                       "which learned reward/value to plan with, by the closed loop", "run"),
    "show": ("show", "ShowConfig", "PRESETS",
             "what trained pendulum models predict near the upright (a figure)", "run"),
}


def _job(name: str):
    """(config class, presets, run(cfg, command)) of a subcommand, its module imported now."""
    import importlib
    module, cls, presets, _, run = COMMANDS[name]
    job = importlib.import_module(f"stride_jax.jobs.{module}")
    cls, presets, fn = getattr(job, cls), getattr(job, presets), getattr(job, run)
    if name == "ppo":  # ppo.run(cfg) takes no command line
        return cls, presets, lambda cfg, command: fn(cfg)
    return cls, presets, fn


def main(argv: list[str] | None = None) -> None:
    args_in = sys.argv[1:] if argv is None else argv
    # before JAX starts: small CPUs deadlock without; datasets are simulated deterministically
    stride_jax.set_xla_flags(deterministic=bool(args_in) and args_in[0] == "data")
    if args_in and args_in[0] == "gap":  # the gap tool has its own subcommands (stride_jax.jobs.gap)
        from stride_jax.jobs import gap
        return gap.main(list(args_in[1:]))
    parser = argparse.ArgumentParser(prog="stride", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    # the subcommand named first gets its flags (its job imported); the others only their help
    chosen = next((a for a in args_in if not a.startswith("-")), None)
    job = _job(chosen) if chosen in COMMANDS else None
    for name, (_, _, _, help_, _) in COMMANDS.items():
        p = sub.add_parser(name, help=help_)
        if name == chosen:
            cls, presets, _ = job
            p.add_argument("--preset", default="default", help=f"one of {', '.join(presets)}")
            config.add_flags(p, cls)
    args = parser.parse_args(args_in)
    cls, presets, run = job
    from stride_jax.robots import RobotError
    from stride_jax.sim.dataset import DatasetError
    from stride_jax.train.loop import TrainingError
    try:
        cfg = config.from_flags(cls, args, config.preset(cls, presets, args.preset))
        run(cfg, "stride " + shlex.join(args_in))
    except (RobotError, DatasetError, TrainingError, ValueError, FileNotFoundError) as e:
        raise SystemExit(f"stride {args.command}: error: {e}") from None


if __name__ == "__main__":
    main()
