"""The ``stride`` command. Each subcommand's flags are derived from its config dataclass.

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
    from stride_jax.control import bench as mppi_bench, closed_loop, learned, ppo
    from stride_jax.eval import table
    from stride_jax.jobs import show
    from stride_jax.sim import bench, collect
    from stride_jax.train import job
    return {
        "data": (collect.DataConfig, collect.PRESETS, "generate a dataset", _run_data),
        "train": (job.TrainConfig, job.PRESETS, "train a dynamics model", _run_train),
        "eval": (table.EvalConfig, table.PRESETS, "Table I metrics of trained runs", _run_eval),
        "bench-sim": (bench.BenchConfig, bench.PRESETS, "simulation throughput", _run_bench),
        "bench-mppi": (mppi_bench.BenchConfig, mppi_bench.PRESETS, "MPPI step latency",
                       _run_bench_mppi),
        "ppo": (ppo.PPOConfig, ppo.PRESETS, "one PPO chunk of a warm-start policy (resumes)",
                lambda cfg, command: ppo.run(cfg)),
        "fit-reward-value": (learned.FitConfig, learned.FIT_PRESETS,
                             "learned reward and value models from a PPO run",
                             lambda cfg, command: learned.fit_from_policy(cfg, command)),
        "closed-loop": (closed_loop.ClosedLoopConfig, closed_loop.PRESETS,
                        "closed-loop MPPI in MJX per model and scenario",
                        lambda cfg, command: closed_loop.run(cfg, command)),
        "show": (show.ShowConfig, show.PRESETS,
                 "what trained pendulum models predict near the upright (a figure)",
                 lambda cfg, command: show.run(cfg, command)),
    }


def _run_data(cfg, command: str) -> None:
    from stride_jax.sim import collect, plots
    explorer = None
    if cfg.policy:
        from stride_jax.control import walk
        explorer = walk.PolicyExplorer(cfg.policy, cfg.action_noise,
                                       max_seconds=cfg.seconds or 60.0)
    ds = collect.generate(cfg, explorer)
    png = plots.dataset_summary(ds)
    m = ds.meta
    print(f"wrote {ds.path}: {m['n_episodes']} episodes x {m['n_steps']} steps of {m['robot']} "
          f"({m['backend']}, {m['generation_seconds']:.1f} s), valid fraction "
          f"{m['valid_fraction']:.2f}; summary plot {png}")


def _run_train(cfg, command: str) -> None:
    from stride_jax.train import job
    job.run(cfg)


def _run_eval(cfg, command: str) -> None:
    from stride_jax.eval import table
    table.run(cfg, command=command)


def _run_bench(cfg, command: str) -> None:
    from stride_jax.sim import bench
    rows = bench.run(cfg, on_row=lambda rows: bench.write(rows, cfg, command))
    print(f"wrote {bench.write(rows, cfg, command)}")


def _run_bench_mppi(cfg, command: str) -> None:
    from stride_jax.control import bench
    rows = bench.run(cfg, command)
    print(f"wrote {cfg.out}/bench_mppi_*.md ({len(rows)} rows)")


def main(argv: list[str] | None = None) -> None:
    stride_jax.set_xla_flags()  # before JAX starts: small CPUs deadlock without
    args_in = sys.argv[1:] if argv is None else argv
    if args_in and args_in[0] == "gap":  # the gap tool has its own subcommands (stride_jax.gap.cli)
        from stride_jax.gap import cli as gap_cli
        return gap_cli.main(list(args_in[1:]))
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
