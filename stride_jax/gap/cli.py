"""``stride gap``: ``diagnose`` a log folder, ``simulate`` "real" logs with hidden effects, ``export``
a simulated dataset as logs, ``bench`` the blind benchmark. Wire with ``gap.cli.main(argv)``."""

from __future__ import annotations

import argparse
import dataclasses
import json
import shlex
import sys

import stride_jax


def _parser() -> argparse.ArgumentParser:
    from stride_jax.gap import bench, diagnose, residual

    p = argparse.ArgumentParser(prog="stride gap", description=__doc__)
    sub = p.add_subparsers(dest="cmd", required=True)
    d = sub.add_parser("diagnose", help="where / which / how far, from a log folder")
    d.add_argument("--robot", required=True)
    d.add_argument("--logs", required=True, help="folder with header.json and one CSV per trajectory")
    d.add_argument("--out", required=True, help="report folder (report.md, diagnosis.json, plots)")
    d.add_argument("--preset", default="default", choices=sorted(diagnose.PRESETS))
    for f in dataclasses.fields(diagnose.DiagnoseConfig):  # scalar fields become flags
        if f.type in ("int", "float"):
            d.add_argument(f"--{f.name.replace('_', '-')}", type=int if f.type == "int" else float,
                           default=None)
    d.add_argument("--residual", choices=residual.WHEN, default=None,
                   help="when to fit the STRIDE residual on top of the best hypothesis")
    d.add_argument("--residual-steps", type=int, default=None, help="its optimiser steps")
    d.add_argument("--residual-validation", type=float, default=None,
                   help="share of the training trajectories held back to stop its training early "
                        "(0: off)")
    s = sub.add_parser("simulate", help="'real' logs: the explorer with hidden effects")
    s.add_argument("--robot", required=True)
    s.add_argument("--out", required=True)
    s.add_argument("--effects", default="{}", help='JSON, e.g. \'{"damping": 0.5, "delay": 3}\'')
    s.add_argument("--trajectories", type=int, default=8)
    s.add_argument("--steps", type=int, default=250)
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--noise", action="store_true", help="add a real robot's sensor noise")
    e = sub.add_parser("export", help="a simulated dataset folder as a log folder")
    e.add_argument("--dataset", required=True)
    e.add_argument("--out", required=True)
    b = sub.add_parser("bench", help="the blind benchmark")
    b.add_argument("--preset", default="tiny", choices=sorted(bench.PRESETS))
    b.add_argument("--out", default="results",
                   help="result folder (<name>.md/json; finished rows in <name>_cases/, which a rerun resumes)")
    b.add_argument("--workers", type=int, default=1,
                   help="diagnoses side by side, one process each (rows do not depend on it)")
    b.add_argument("--threads", type=int, default=1,
                   help="MuJoCo rollout threads per worker (with --workers > 1; workers x threads <= cores)")
    b.add_argument("--minutes", type=float, default=None,
                   help="start no new case after this long, then exit 0 (rerun the same command to continue)")
    return p


def _diagnose_config(args: argparse.Namespace):
    """The preset with the flags given on top (``ValueError`` for bad values)."""
    from stride_jax.gap import diagnose

    cfg = diagnose.PRESETS[args.preset]
    over = {f.name: getattr(args, f.name) for f in dataclasses.fields(cfg)
            if f.name != "residual" and getattr(args, f.name, None) is not None}
    res = {k: v for k, v in (("when", args.residual), ("steps", args.residual_steps),
                             ("validation", args.residual_validation)) if v is not None}
    if res:
        over["residual"] = dataclasses.replace(cfg.residual, **res)
    return dataclasses.replace(cfg, **over)


def main(argv: list[str] | None = None) -> int:
    stride_jax.set_xla_flags()  # before JAX starts: small CPUs deadlock without
    argv = list(sys.argv[1:] if argv is None else argv)
    args = _parser().parse_args(argv)
    from stride_jax.gap import logs

    try:
        if args.cmd == "diagnose":
            from stride_jax.gap import diagnose, report
            from stride_jax.sim import model

            try:
                cfg = _diagnose_config(args)
            except ValueError as err:
                print(f"error: {err}", file=sys.stderr)
                return 2
            sm = model.load(args.robot)
            _, trajs = logs.read(args.logs, sm)
            d = diagnose.diagnose(sm, trajs, cfg)
            path = report.write(d, args.out, "stride gap " + shlex.join(argv))
            print(f"report: {path}")
        elif args.cmd == "simulate":
            from stride_jax.gap import real
            from stride_jax.sim import model

            sm = model.load(args.robot)
            _, logged = real.generate(sm, json.loads(args.effects), args.trajectories, args.steps,
                                      args.seed, real.SensorNoise() if args.noise else None)
            logs.write(args.out, sm, logged, notes="simulated by `stride gap " + shlex.join(argv) + "`")
            print(f"{len(logged)} trajectories in {args.out}")
        elif args.cmd == "export":
            print(logs.export_dataset(args.dataset, args.out))
        elif args.cmd == "bench":
            from stride_jax.gap import bench

            try:
                bench.run(bench.PRESETS[args.preset], args.out, command="stride gap " + shlex.join(argv),
                          log=lambda line: print(line, flush=True), workers=args.workers, threads=args.threads,
                          minutes=args.minutes)
            except bench.BenchError as err:  # rows on disk from another config, bad --workers/--threads
                print(f"error: {err}", file=sys.stderr)
                return 2
    except logs.LogError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
