"""Gaits as parameter settings (issue 4, variable gait): the named gaits' references alone in
MJX, and the gait MPPI settles on when it plans frequency, duty and phase offsets itself.

    python experiments/closed_loop_gait.py --preset tiny    # CPU, seconds
    python experiments/closed_loop_gait.py --preset gpu     # one GPU, minutes
"""

import stride_jax
from stride_jax import config
from stride_jax.jobs import gait_study

if __name__ == "__main__":
    stride_jax.set_xla_flags()  # before JAX starts: small CPUs deadlock without
    config.config_main("python experiments/closed_loop_gait.py", gait_study.GaitStudyConfig,
                       gait_study.GAIT_PRESETS, gait_study.gait_study,
                       description=__doc__.split("\n")[0])
