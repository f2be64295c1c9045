"""The paper's Table I: data, every model x seeds, evaluation -> results/table1/<robot>/table.{md,json}.

    python experiments/table1.py --robot go1,g1                    # full size (use a GPU)
    python experiments/table1.py --robot go1 --preset tiny          # minutes on a CPU
    python experiments/table1.py --robot go1 --minutes 7            # stop cleanly, resume later
    python experiments/table1.py --robot go1 --data walk            # walking, stochastic ground

``--data`` picks the dataset: ``explore`` (the robot's own explorer, per-episode randomisation:
the datasets of the first Table I) or ``walk`` (the trained PPO policy of ``results/policies/``
walking under velocity commands with noise on its actions, on ground patches of varying friction
and softness with several pushes: a contact residual that is stochastic given the state). The
walk variant's folders and results carry ``_walk`` (``results/table1/go1_walk/``).

Runs train side by side (``--parallel`` processes share the device: the models are small, so one
process leaves a GPU idle between kernel launches). Seeds of one model compile to the same
programs, so the seed-0 run of each (robot, model) goes first and the others start once it has
filled JAX's persistent compilation cache (its first validation). Every run is resumable: run
the same command again and finished runs are skipped, stopped ones resume from their last
checkpoint, and evaluations are reused. Logs: ``<runs>/<model>-s<seed>/{train,eval}.log``
(``--side-by-side``: ``<runs>/<model>-s0+1+2.train.log``).
"""

from __future__ import annotations

import argparse
import dataclasses
import pathlib
import shlex
import subprocess
import sys
import time

import stride_jax
from stride_jax import config
from stride_jax.jobs import pool


@dataclasses.dataclass(frozen=True)
class Table1Preset:
    """The jobs' presets one table size runs.

    Attributes:
      episodes: data episodes (``stride data --episodes``).
      train: the ``stride train`` preset (its steps unless ``steps`` is given).
      eval: the ``stride eval`` preset.
      data: the ``stride data`` preset.
      steps: training steps (0: the training preset's).
    """

    episodes: int
    train: str
    eval: str = "default"
    data: str = "default"
    steps: int = 0


PRESETS = {
    "tiny": Table1Preset(episodes=8, train="tiny", eval="tiny"),
    # CPU-sized: the training default (128 x 3, batch 256) on 96 episodes, tens of minutes
    "cpu": Table1Preset(episodes=96, train="default", steps=4000),
    # the training preset `paper` is the committed tables' (12k steps; the G1's ran --steps 8000)
    "paper": Table1Preset(episodes=1024, train="paper", data="paper"),
}
MODELS = ("stride", "delan", "delan_prior", "lnn_diffusion", "onn", "diffusion")
DATA = {"explore": [], "walk": ["--stochastic", "--policy", "{policy}",
                                 "--action-noise", "{noise}"]}
# Largest per-episode action noise of the walking data: on stochastic ground the G1 fell in 3 of 6
# episodes at 0.3 (valid fraction 0.78) and kept a valid fraction of 0.99 at 0.1 (6 x 6 s each).
WALK_NOISE = {"g1": 0.1}


@dataclasses.dataclass(frozen=True)
class Table1Config:
    """What ``experiments/table1.py`` runs (lists are comma-separated strings).

    Attributes:
      robot: robots.
      preset: one of :data:`PRESETS` (data size, training and evaluation presets).
      data: the dataset kind, one of :data:`DATA`.
      data_policy: the PPO run whose walk makes the ``walk`` data (default
        ``results/policies/ppo_<robot>``); another gets data and runs folders of its own
        (``<robot>_walk_<its folder's name>``): models trained on the gait of the policy the
        planner will sample around.
      seeds, models: training seeds and models.
      ablation: extra STRIDE runs (first seed) trained with these ``--acc-through`` choices,
        e.g. ``prior,sample``.
      ablation_seeds: train the ablation runs on every seed, not only the first.
      steps: training steps (0: the training preset's).
      stop_at: stop every run after this many steps while its learning-rate schedule spans
        ``steps`` (``stride train --stop-at``; 0: run to ``steps``): seeds trained to the step
        where another seed of the same schedule stopped.
      transition_weight: ``stride train --transition-weight`` for every run (the structured
        models' one-control-period transition loss; 0: the paper's training). Non-zero weights
        get their own runs and results folders (``<robot>[_<data>]_tw<weight>``).
      transition_fraction: ``stride train --transition-fraction``: the share of each minibatch
        the transition term is computed on (1: all; below 1 the folders gain ``_tf<fraction>``).
      base_weight: ``stride train --base-weight`` for every run (a floating base's dofs' weight
        in the one-period losses: the structured models' transition term, which it needs, and
        ONN's loss; 1: every dof alike); other weights get their own folders (``..._bw<weight>``).
      potential: ``stride train --potential`` for the structured runs (``net``, the paper's
        ``V = m g z + V_net``, or ``com``: gravity's multibody form, ``LNNConfig.potential``);
        ``com`` gets its own runs and results folders (``..._com``).
      slope_deg: sloped data (``stride data --slope-deg``: each episode's gravity tilted under
        the floor by up to this many degrees) and every model trained with
        ``--gravity-context`` (its networks see the slope); data and folders ``..._slope<deg>``.
      parallel: processes at once.
      side_by_side: train each model's seeds in one ``stride train --seeds`` process (one program,
        the seeds vmapped; ``<robot>/<model>-s0+1+2`` in the progress): on a GPU at the paper's
        size three Go1 seeds take 1.4x one seed's step, a whole three-seed run 1.7x less time
        than three one after another (``results/throughput/README.md``). Processes side by side
        share a GPU by time slices (the closed loop's measured 2-3x slower per step each); the
        two were not timed against each other for training. On a CPU no gain.
      minutes: wall-clock budget for training, from when the data exist (0: none); runs stop
        cleanly at it.
      eval_only: evaluate and tabulate the runs already trained (no data, no training).
      root: data and runs folder (default: ``data/``, ``runs/``).
      out: results folder (default: ``results/table1/<robot>``).
    """

    robot: str = "go1"
    preset: str = "paper"
    data: str = "explore"
    data_policy: str = ""
    seeds: str = "0,1,2"
    models: str = ",".join(MODELS)
    ablation: str = ""
    ablation_seeds: bool = False
    steps: int = 0
    stop_at: int = 0
    transition_weight: float = 0.0
    transition_fraction: float = 1.0
    base_weight: float = 1.0
    potential: str = "net"
    slope_deg: float = 0.0
    parallel: int = 5
    side_by_side: bool = False
    minutes: float = 0.0
    eval_only: bool = False
    root: str = ""
    out: str = ""


def folder_suffixes(args: Table1Config) -> tuple[str, str]:
    """``(data, variant)``: the suffixes of the data's folder (``<robot><data>-<preset>``: the
    data kind, the data policy's folder name, the slope) and of the runs' (``<robot><data>
    <variant>-<preset>``: the transition loss, its fraction, the base's weight, the potential).
    ``experiments/table1_device.sh`` builds the same names (tested)."""
    data = "" if args.data == "explore" else f"_{args.data}"
    data += f"_{pathlib.Path(args.data_policy).name}" if args.data_policy else ""
    data += f"_slope{args.slope_deg:g}" if args.slope_deg else ""
    variant = f"_tw{args.transition_weight:g}" if args.transition_weight else ""
    variant += f"_tf{args.transition_fraction:g}" if args.transition_fraction < 1 else ""
    variant += f"_bw{args.base_weight:g}" if args.base_weight != 1 else ""
    variant += f"_{args.potential}" if args.potential != "net" else ""
    return data, variant


def tag(model: str, variant: str) -> str:
    """A run's model and ``--acc-through`` variant as its folder names them."""
    return f"{model}-{variant}" if variant else model


def run_name(robot: str, model: str, seed: int, variant: str) -> str:
    """``<robot>/<model>[-<variant>]-s<seed>``: a run's name in the progress and the logs."""
    return f"{robot}/{tag(model, variant)}-s{seed}"


def training_groups(jobs: list[tuple], side_by_side: bool) -> dict[str, list[tuple]]:
    """The training processes over ``jobs`` ``(robot, model, seed, variant)``: one per run, named
    as the run, or with ``side_by_side`` one per robot, model and variant over its seeds
    (``<robot>/<model>-s0+1+2``: one ``stride train --seeds`` program); a group of one seed (the
    ablation's first-seed runs) keeps its run's name."""
    groups: dict[str, list[tuple]] = {}
    for r, m, s, v in jobs:
        groups.setdefault(f"{r}/{tag(m, v)}" if side_by_side else run_name(r, m, s, v), []).append((r, m, s, v))
    if not side_by_side:
        return groups
    return {(k + "-s" + "+".join(str(j[2]) for j in g)) if len(g) > 1 else run_name(*g[0]): g
            for k, g in groups.items()}


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    config.add_flags(p, Table1Config, choices={"preset": tuple(PRESETS), "data": tuple(DATA)})
    args = config.from_flags(Table1Config, p.parse_args(argv))
    preset = PRESETS[args.preset]
    steps = args.steps or preset.steps
    root = pathlib.Path(args.root or ".")
    robots = [r for r in args.robot.split(",") if r]
    command = "python experiments/table1.py " + shlex.join(sys.argv[1:] if argv is None else argv)
    t0 = time.time()
    env = pool.shared_env(root)
    if args.data_policy and args.data != "walk":
        raise SystemExit(f"--data-policy needs --data walk (the {args.data} data has no policy)")
    if args.transition_fraction < 1 and not args.transition_weight:
        raise SystemExit(f"--transition-fraction {args.transition_fraction:g} needs "
                         "--transition-weight above 0")
    if args.base_weight != 1 and not args.transition_weight:
        raise SystemExit(f"--base-weight {args.base_weight:g} needs --transition-weight above 0 "
                         "(it weighs the structured models' transition term)")
    suffix, variant = folder_suffixes(args)
    tf = args.transition_fraction
    data = {r: root / "data" / f"{r}{suffix}-{args.preset}" for r in robots}
    runs = {r: root / "runs" / f"{r}{suffix}{variant}-{args.preset}" for r in robots}

    gen = {f"data-{r}": pool.stride_command("data", "--robot", r, "--preset", preset.data,
                                            "--episodes", str(preset.episodes),
                                            *[a.format(robot=r, noise=WALK_NOISE.get(r, 0.3),
                                                       policy=args.data_policy
                                                       or f"results/policies/ppo_{r}")
                                              for a in DATA[args.data]],
                                            *(["--slope-deg", f"{args.slope_deg:g}"]
                                              if args.slope_deg else []),
                                            "--out", str(data[r]))
           for r in robots if not (data[r] / "meta.json").exists() and not args.eval_only}
    failed = pool.run(gen, {n: root / "logs" / f"{n}.log" for n in gen}, args.parallel, env,
                      t0=t0)
    if failed:
        raise SystemExit(f"data generation failed: {failed} (see {root / 'logs'})")
    # The training budget starts once the data exist (measured on an H100: generating two Go1
    # datasets side by side took 145 s of a 5-minute budget that had counted from the start).
    deadline = time.time() + 60 * args.minutes if args.minutes else 0.0

    seeds = [int(s) for s in args.seeds.split(",")]
    first_seed = seeds[0]
    # (robot, model, seed, acc_through variant or "" for the default)
    jobs = [(r, m, s, "") for s in seeds for r in robots
            for m in args.models.split(",")]
    ablation_seeds = seeds if args.ablation_seeds else [first_seed]
    jobs += [(r, "stride", s, v) for s in ablation_seeds for r in robots
             for v in args.ablation.split(",") if v]
    run_dir = lambda r, m, s, v: runs[r] / f"{tag(m, v)}-s{s}"
    folders = {run_name(*j): run_dir(*j) for j in jobs}
    groups = training_groups(jobs, args.side_by_side)

    def train_command(group):
        r, m, s, v = group[0]
        who = (["--seeds", ",".join(str(j[2]) for j in group), "--out", str(runs[r] / tag(m, v))]
               if args.side_by_side else ["--seed", str(s), "--out", str(run_dir(r, m, s, v))])
        return pool.stride_command(
            "train", "--robot", r, "--model", m, "--preset", preset.train,
            *(["--steps", str(steps)] if steps else []),
            *who, "--data", str(data[r]),
            "--deadline", str(deadline), *(["--acc-through", v] if v else []),
            *(["--stop-at", str(args.stop_at)] if args.stop_at else []),
            *(["--transition-weight", f"{args.transition_weight:g}"] if args.transition_weight else []),
            *(["--transition-fraction", f"{tf:g}"] if tf < 1 else []),
            *(["--base-weight", f"{args.base_weight:g}"] if args.base_weight != 1 else []),
            *(["--potential", args.potential] if args.potential != "net" else []),
            *(["--gravity-context"] if args.slope_deg else []))

    train = {g: train_command(members) for g, members in groups.items()}
    logs = {g: (runs[members[0][0]] / f"{g.split('/', 1)[1]}.train.log" if args.side_by_side
                else folders[run_name(*members[0])] / "train.log") for g, members in groups.items()}
    # one seed's run first where seeds train one by one: the others reuse its compilation
    leader = {g: run_dir(m[0][0], m[0][1], first_seed, "") for g, m in groups.items()}
    follows = lambda g: (lambda: args.side_by_side or leader[g] == folders[run_name(*groups[g][0])]
                         or (leader[g] / "metrics.csv").exists())
    ready = {g: follows(g) for g in train}
    if args.eval_only:
        failed = []
        ok = [run_name(*j) for j in jobs if (folders[run_name(*j)] / "summary.json").exists()]
    else:
        failed = pool.run(train, logs, args.parallel, env, ready, t0, "train")
        ok = [run_name(*j) for g, members in groups.items() if g not in failed for j in members]
    # Evaluate runs side by side (each caches its eval.json), then tabulate per robot. The first
    # evaluation of a robot goes alone: it re-simulates the true continuations every other
    # evaluation of that dataset reuses.
    evals = {n: pool.stride_command("eval", "--preset", preset.eval, "--runs",
                                    str(folders[n]), "--out", str(folders[n] / "eval_out"))
             for n in ok}
    first = {r: next((folders[n] for n in evals if n.startswith(f"{r}/")), None) for r in robots}
    ready = {n: (lambda n=n: folders[n] == first[n.split("/")[0]]
                 or (first[n.split("/")[0]] / "eval.json").exists()) for n in evals}
    failed += pool.run(evals, {n: folders[n] / "eval.log" for n in evals}, args.parallel, env,
                       ready, t0, "eval")
    for r in robots:
        mine = [str(folders[n]) for n in ok if n.startswith(f"{r}/") and n not in failed]
        if not mine:
            continue
        out = args.out or f"results/table1/{r}{suffix}{variant}"
        subprocess.run(pool.stride_command("eval", "--preset", preset.eval, "--runs",
                                           ",".join(mine), "--out", out, "--label", command),
                       check=True, env=env)
        print(f"[{time.time() - t0:.0f} s] wrote {out}/table.md", flush=True)
    if failed:
        raise SystemExit(f"failed: {failed} (see their logs)")


if __name__ == "__main__":
    stride_jax.set_xla_flags()  # before JAX starts: small CPUs deadlock without
    main()
