"""The paper's figures and claims on our data -> results/reproduce/*.png, *.json, summary.json.

    python experiments/reproduce.py --preset tiny --root /tmp/repro     # every part on a CPU
    python experiments/reproduce.py --preset paper                      # a GPU; Go1/G1 runs from
        # `python experiments/table1.py --robot go1,g1 --preset paper` under the same --root
    python experiments/reproduce.py --preset tiny --parts phase,allocation
    python experiments/reproduce.py --preset paper --parallel 12     # pendulum runs side by side

``--parallel N`` first trains the pendulum runs the parts need as N processes at once (small
models leave a GPU idle between kernel launches); the parts then find them finished.

Parts: phase (pendulum phase portrait), allocation (bouncing pendulum residual share), nfe (CFM
vs DDPM: error and Hz vs NFE, Go1), horizon (error vs horizon, five models, Go1 and G1), forces
(vertical GRF per foot, Go1 gaits and G1). Every flag is a field of
``stride_paper.figures.ReproduceConfig``; the preset fills the rest. Re-running resumes:
finished runs and cached evaluations are reused.
"""

from __future__ import annotations

import argparse
import os
import pathlib
import shlex
import sys
import time

import stride_jax
from stride_jax import config

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))  # stride_paper, if not installed


def main(argv: list[str] | None = None) -> dict:
    from stride_paper import figures

    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--preset", default="tiny", help=f"one of {', '.join(figures.PRESETS)}")
    p.add_argument("--parallel", type=int, default=1,
                   help="train the pendulum runs this many at a time first (1: in the parts)")
    config.add_flags(p, figures.ReproduceConfig)
    args = p.parse_args(argv)
    cfg = config.from_flags(figures.ReproduceConfig, args,
                            config.preset(figures.ReproduceConfig, figures.PRESETS, args.preset))
    command = "python experiments/reproduce.py " + shlex.join(sys.argv[1:] if argv is None
                                                              else argv)
    if args.parallel > 1:  # the training processes share the device with this one
        os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
    import jax

    # Seeds of one model compile to the same programs (parameters are arguments): share them.
    jax.config.update("jax_compilation_cache_dir",
                      str((pathlib.Path(cfg.root) / ".jax_cache").absolute()))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    t0 = time.time()
    if args.parallel > 1:
        _pretrain(cfg, args.preset, args.parallel, t0)
    summary = figures.run(cfg, args.preset, command,
                          log=lambda s: print(f"[{time.time() - t0:.0f} s] {s}", flush=True))
    print(f"wrote {cfg.out}/summary.json ({', '.join(summary['seconds'])}; "
          f"{sum(summary['seconds'].values()):.0f} s)")
    return summary


def _pretrain(cfg, preset: str, parallel: int, t0: float) -> None:
    """The pendulum runs of the selected parts, ``parallel`` ``stride train`` processes at once."""
    from stride_jax.jobs import pool
    from stride_jax.eval import runs
    from stride_paper import figure_runs

    tag = cfg.tag or preset
    jobs = [tc for tc in figure_runs.pendulum_jobs(cfg, tag)
            if not runs.is_finished(pathlib.Path(tc.out))]
    for robot in sorted({tc.robot for tc in jobs}):
        figure_runs.ensure_pendulum_data(cfg, tag, robot)
    env = pool.shared_env(cfg.root)
    cmds = {tc.out: pool.stride_command("train", *pool.config_flags(tc)) for tc in jobs}
    failed = pool.run(cmds, {n: pathlib.Path(n) / "train.log" for n in cmds}, parallel, env,
                      t0=t0, what="train")
    if failed:
        raise SystemExit(f"training failed: {failed} (see their train.log)")


if __name__ == "__main__":
    stride_jax.set_xla_flags()  # before JAX starts: small CPUs deadlock without
    main()
