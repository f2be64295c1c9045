"""Gaits as parameter settings (issue 4, variable gait): the named gaits' references alone in
MJX, and the gait MPPI settles on when it plans frequency, duty and phase offsets itself.

    python experiments/closed_loop_gait.py --preset tiny    # CPU, seconds
    python experiments/closed_loop_gait.py --preset gpu     # one GPU, minutes
"""

import argparse
import shlex
import sys

import stride_jax  # noqa: F401  (XLA flags before JAX initialises)
from stride_jax import cli
from stride_jax.control import gait_study

if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--preset", default="default",
                        help=f"one of {', '.join(gait_study.GAIT_PRESETS)}")
    cli._add_config_args(parser, gait_study.GaitStudyConfig)
    args = parser.parse_args()
    cfg = cli._config(gait_study.GaitStudyConfig, gait_study.GAIT_PRESETS, args)
    gait_study.gait_study(cfg, shlex.join(["python", "experiments/closed_loop_gait.py",
                                            *sys.argv[1:]]), log=lambda s: print(s, flush=True))
