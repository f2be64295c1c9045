"""``stride gap``: ``diagnose`` a log folder, ``simulate`` "real" logs with hidden effects, ``import``
recordings (ROS 2 bags, MCAP, CSV) as logs, ``export`` a simulated dataset as logs, ``bench`` the
blind benchmark (:mod:`stride_jax.jobs.gap_bench`), ``bench-independent`` the blind benchmark on
logs from independent code and simulator settings (:mod:`stride_jax.jobs.gap_bench_independent`).
``stride gap ARGS`` calls ``main(ARGS)``."""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import shlex
import sys

import stride_jax
from stride_jax import config


@dataclasses.dataclass(frozen=True)
class DiagnoseJob:
    """``stride gap diagnose``: which robot, which log folder, where the report goes; the
    diagnosis settings are :class:`~stride_jax.gap.diagnose.DiagnoseConfig`'s flags on top of
    ``--preset`` (nested ones dotted: ``--residual.when always``, ``--fit.grid 7``).

    Attributes:
      robot: the nominal robot model: a registered name (``stride_jax.robots``), an MJCF file
        (.xml) or a robot/mapping file with a [robot] table (.toml).
      logs: folder with header.json and one CSV per trajectory.
      out: report folder (report.md, diagnosis.json, plots).
      nominal: the nominal model's form: ``shipped`` (the MJCF as shipped: its own cone,
        contacts, time step) or ``training`` (the robot's MJX-training edits; the same model for
        robots without them).
    """

    robot: str = ""
    logs: str = ""
    out: str = ""
    nominal: str = "shipped"


@dataclasses.dataclass(frozen=True)
class SimulateJob:
    """``stride gap simulate``: "real" logs, the robot's explorer with hidden effects.

    Attributes:
      robot: the robot.
      out: log folder to write.
      effects: JSON, e.g. ``'{"damping": 0.5, "delay": 3}'``.
      trajectories, steps: how many logged trajectories, and control steps each.
      seed: explorer and effect draws.
      noise: add a real robot's sensor noise.
      nominal: the model the "real" robot is simulated with (``shipped`` or ``training``, as
        for ``diagnose``).
    """

    robot: str = ""
    out: str = ""
    effects: str = "{}"
    trajectories: int = 8
    steps: int = 250
    seed: int = 0
    noise: bool = False
    nominal: str = "shipped"


@dataclasses.dataclass(frozen=True)
class ImportJob:
    """``stride gap import``: recordings (the positional arguments: ROS 2 bag folders, ``.mcap``,
    ``.db3`` or ``.csv`` files) as a log folder, through a mapping file
    (:mod:`stride_jax.gap.importer`).

    Attributes:
      mapping: the mapping file (TOML): robot, joint names, column sources.
      out: log folder to write.
    """

    mapping: str = ""
    out: str = ""


@dataclasses.dataclass(frozen=True)
class ExportJob:
    """``stride gap export``: a simulated dataset folder as a log folder.

    Attributes:
      dataset: the dataset folder (``stride data``).
      out: log folder to write.
    """

    dataset: str = ""
    out: str = ""


@dataclasses.dataclass(frozen=True)
class BenchJob:
    """``stride gap bench``: the blind benchmark (cases from ``--preset``, a name of
    ``stride_jax.jobs.gap_bench.PRESETS``).

    Attributes:
      out: result folder (<name>.md/json; finished rows in <name>_cases/, which a rerun resumes).
      workers: diagnoses side by side, one process each (rows do not depend on it).
      threads: MuJoCo rollout threads per worker (with workers > 1; workers x threads <= cores).
      minutes: start no new case after this long, then exit 0 (rerun the same command to
        continue); inf: no limit.
    """

    out: str = "results"
    workers: int = 1
    threads: int = 1
    minutes: float = math.inf


# Spellings of the diagnosis flags before they were derived from the nested config.
_DIAGNOSE_ALIASES = {"residual.when": "--residual", "residual.steps": "--residual-steps",
                     "residual.validation": "--residual-validation"}


def _parser() -> argparse.ArgumentParser:
    from stride_jax.gap import diagnose, nominal, residual
    from stride_jax.jobs import gap_bench_independent as bench_independent
    from stride_jax.jobs import gap_bench as bench

    p = argparse.ArgumentParser(prog="stride gap", description=__doc__)
    sub = p.add_subparsers(dest="cmd", required=True)
    d = sub.add_parser("diagnose", help="where / which / how far, from a log folder")
    config.add_flags(d, DiagnoseJob, required=("robot", "logs", "out"), choices={"nominal": nominal.FORMS})
    d.add_argument("--preset", default="default", choices=sorted(diagnose.PRESETS))
    config.add_flags(d, diagnose.DiagnoseConfig, aliases=_DIAGNOSE_ALIASES,
                     choices={"residual.when": residual.WHEN})
    s = sub.add_parser("simulate", help="'real' logs: the explorer with hidden effects")
    config.add_flags(s, SimulateJob, required=("robot", "out"), choices={"nominal": nominal.FORMS})
    i = sub.add_parser("import", help="recordings (ROS 2 bags, MCAP, CSV) as a log folder")
    config.add_flags(i, ImportJob, required=("mapping", "out"))
    i.add_argument("files", nargs="+", help="bag folders, .mcap, .db3 or .csv files")
    e = sub.add_parser("export", help="a simulated dataset folder as a log folder")
    config.add_flags(e, ExportJob, required=("dataset", "out"))
    b = sub.add_parser("bench", help="the blind benchmark")
    b.add_argument("--preset", default="tiny", choices=sorted(bench.PRESETS))
    config.add_flags(b, BenchJob)
    bi = sub.add_parser("bench-independent", help="the blind benchmark on logs from independent code and "
                        "simulator settings (stride_jax.jobs.gap_bench_independent)")
    bi.add_argument("--preset", default="tiny", choices=sorted(bench_independent.PRESETS))
    config.add_flags(bi, BenchJob)
    return p


def _effects_flag(text: str) -> dict:
    """``--effects``: a JSON object of library effect -> parameter (a number or a list); a
    ``ValueError`` naming what is wrong otherwise."""
    from stride_jax.gap import effects

    try:
        planted = json.loads(text)
    except json.JSONDecodeError as err:
        raise ValueError(f"--effects {text!r} is not JSON ({err}); give an object such as "
                         "'{\"damping\": 0.3}'") from None
    if not isinstance(planted, dict):
        raise ValueError(f"--effects {text!r} must be a JSON object of effect -> parameter, "
                         "such as '{\"damping\": 0.3}'")
    unknown = [n for n in planted if n not in effects.ALL]
    if unknown:
        raise ValueError(f"--effects: unknown effect(s) {unknown}; known: {', '.join(effects.ALL)}")
    return planted


def _diagnose_config(args: argparse.Namespace):
    """The preset with the flags given on top (``ValueError`` for bad values)."""
    from stride_jax.gap import diagnose

    return config.from_flags(diagnose.DiagnoseConfig, args, diagnose.PRESETS[args.preset])


def main(argv: list[str] | None = None) -> int:
    stride_jax.set_xla_flags()  # before JAX starts: small CPUs deadlock without
    argv = list(sys.argv[1:] if argv is None else argv)
    args = _parser().parse_args(argv)
    job = {"diagnose": DiagnoseJob, "simulate": SimulateJob, "import": ImportJob, "export": ExportJob,
           "bench": BenchJob, "bench-independent": BenchJob}[args.cmd]
    j = config.from_flags(job, args)
    from stride_jax.gap import logs
    from stride_jax.robots.base import RobotError

    try:
        if args.cmd == "diagnose":
            from stride_jax.gap import diagnose, nominal
            from stride_jax.jobs import gap_report as report
            from stride_jax.sim import model

            try:
                cfg = _diagnose_config(args)
            except ValueError as err:
                print(f"error: {err}", file=sys.stderr)
                return 2
            sm = nominal.load(j.robot, j.nominal)
            h, trajs = logs.read(j.logs, sm)
            d = diagnose.diagnose(sm, trajs, cfg, velocity_std=logs.velocity_std(h, sm))
            path = report.write(d, j.out, "stride gap " + shlex.join(argv))
            print(f"report: {path}")
        elif args.cmd == "simulate":
            from stride_jax.gap import nominal, real

            try:
                planted = _effects_flag(j.effects)
            except ValueError as err:
                print(f"error: {err}", file=sys.stderr)
                return 2
            sm = nominal.load(j.robot, j.nominal)
            _, logged = real.generate(sm, planted, j.trajectories, j.steps,
                                      j.seed, real.SensorNoise() if j.noise else None)
            logs.write(j.out, sm, logged, notes="simulated by `stride gap " + shlex.join(argv) + "`")
            print(f"{len(logged)} trajectories in {j.out}")
        elif args.cmd == "import":
            from stride_jax.gap import importer

            print(f"log folder: {importer.run(j.mapping, args.files, j.out)}")
        elif args.cmd == "export":
            print(logs.export_dataset(j.dataset, j.out))
        elif args.cmd == "bench":
            from stride_jax.jobs import gap_bench as bench

            try:
                bench.run(bench.PRESETS[args.preset], j.out, command="stride gap " + shlex.join(argv),
                          log=lambda line: print(line, flush=True), workers=j.workers, threads=j.threads,
                          minutes=None if math.isinf(j.minutes) else j.minutes)
            except bench.BenchError as err:  # rows on disk from another config, bad --workers/--threads
                print(f"error: {err}", file=sys.stderr)
                return 2
        elif args.cmd == "bench-independent":
            from stride_jax.jobs import gap_bench as bench, gap_bench_independent as bench_independent

            try:
                bench_independent.run(bench_independent.PRESETS[args.preset], j.out,
                                      command="stride gap " + shlex.join(argv), log=lambda line: print(line, flush=True),
                                      workers=j.workers, threads=j.threads,
                                      minutes=None if math.isinf(j.minutes) else j.minutes)
            except bench.BenchError as err:
                print(f"error: {err}", file=sys.stderr)
                return 2
    except (logs.LogError, RobotError) as err:  # bad logs, mapping, recordings or robot file
        print(f"error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
