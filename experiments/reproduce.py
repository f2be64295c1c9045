"""The paper's figures and claims on our data -> results/reproduce/*.png, *.json, summary.json.

    python experiments/reproduce.py --preset tiny --root /tmp/repro     # every part on a CPU
    python experiments/reproduce.py --preset paper                      # a GPU; Go1/G1 runs from
        # `python experiments/table1.py --robot go1,g1 --preset paper` under the same --root
    python experiments/reproduce.py --preset tiny --parts phase,allocation

Parts: phase (pendulum phase portrait), allocation (bouncing pendulum residual share), nfe (CFM
vs DDPM: error and Hz vs NFE, Go1), horizon (error vs horizon, five models, Go1 and G1), forces
(vertical GRF per foot, Go1 gaits and G1). Every flag is a field of
``stride_jax.eval.figures.ReproduceConfig``; the preset fills the rest. Re-running resumes:
finished runs and cached evaluations are reused.
"""

from __future__ import annotations

import argparse
import pathlib
import shlex
import sys
import time

import stride_jax  # noqa: F401  (XLA flags before JAX initialises)
from stride_jax import cli


def main(argv: list[str] | None = None) -> dict:
    from stride_jax.eval import figures

    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--preset", default="tiny", help=f"one of {', '.join(figures.PRESETS)}")
    cli._add_config_args(p, figures.ReproduceConfig)
    args = p.parse_args(argv)
    cfg = cli._config(figures.ReproduceConfig, figures.PRESETS, args)
    command = "python experiments/reproduce.py " + shlex.join(sys.argv[1:] if argv is None
                                                              else argv)
    import jax

    # Seeds of one model compile to the same programs (parameters are arguments): share them.
    jax.config.update("jax_compilation_cache_dir",
                      str((pathlib.Path(cfg.root) / ".jax_cache").absolute()))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    t0 = time.time()
    summary = figures.run(cfg, args.preset, command,
                          log=lambda s: print(f"[{time.time() - t0:.0f} s] {s}", flush=True))
    print(f"wrote {cfg.out}/summary.json ({', '.join(summary['seconds'])}; "
          f"{sum(summary['seconds'].values()):.0f} s)")
    return summary


if __name__ == "__main__":
    main()
