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
    stride show [--stride runs/pendulum/stride --baseline runs/pendulum/delan --phase.grid 15]
    stride gap diagnose --robot go1 --logs DIR --out DIR   (also: gap simulate, import, export, bench)
"""

from __future__ import annotations

import argparse
import shlex
import sys

import stride_jax
from stride_jax import config


def _commands():
    """name -> (config class, presets, help, run(cfg, command))."""
    from stride_jax.jobs import (bench_mppi, bench_sim, closed_loop, data, eval as eval_job,
                                 fit_reward_value, ppo, show, train)
    return {
        "data": (data.DataConfig, data.PRESETS, "generate a dataset", data.run),
        "train": (train.TrainConfig, train.PRESETS, "train a dynamics model", train.run),
        "eval": (eval_job.EvalConfig, eval_job.PRESETS, "Table I metrics of trained runs",
                 eval_job.run),
        "bench-sim": (bench_sim.BenchConfig, bench_sim.PRESETS, "simulation throughput",
                      bench_sim.run),
        "bench-mppi": (bench_mppi.BenchConfig, bench_mppi.PRESETS, "MPPI step latency",
                       bench_mppi.run),
        "ppo": (ppo.PPOConfig, ppo.PRESETS, "one PPO chunk of a warm-start policy (resumes)",
                lambda cfg, command: ppo.run(cfg)),
        "fit-reward-value": (fit_reward_value.FitConfig, fit_reward_value.FIT_PRESETS,
                             "learned reward and value models from a PPO run",
                             fit_reward_value.fit_from_policy),
        "closed-loop": (closed_loop.ClosedLoopConfig, closed_loop.PRESETS,
                        "closed-loop MPPI in MJX per model and scenario", closed_loop.run),
        "show": (show.ShowConfig, show.PRESETS,
                 "what trained pendulum models predict near the upright (a figure)", show.run),
    }


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
    commands = _commands()
    for name, (cls, presets, help_, _) in commands.items():
        p = sub.add_parser(name, help=help_)
        p.add_argument("--preset", default="default", help=f"one of {', '.join(presets)}")
        config.add_flags(p, cls)
    args = parser.parse_args(argv)
    cls, presets, _, run = commands[args.command]
    from stride_jax.robots import RobotError
    from stride_jax.sim.dataset import DatasetError
    from stride_jax.train.loop import TrainingError
    try:
        cfg = config.from_flags(cls, args, config.preset(cls, presets, args.preset))
        run(cfg, "stride " + shlex.join(sys.argv[1:] if argv is None else argv))
    except (RobotError, DatasetError, TrainingError, ValueError, FileNotFoundError) as e:
        raise SystemExit(f"stride {args.command}: error: {e}") from None


if __name__ == "__main__":
    main()
