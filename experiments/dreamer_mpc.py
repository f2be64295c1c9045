"""Dreamer-MPC ablation in closed loop (issue 19, item 2): the policy alone, MPPI through a
learned model as today, and the Dreamer-MPC switches one at a time
(:mod:`stride_jax.jobs.dreamer_mpc`).

    python experiments/dreamer_mpc.py --preset tiny      # CPU
    python experiments/dreamer_mpc.py --preset gpu       # one H100

Writes ``ablation.{json,md}``, the planner's value (``value/``) and one closed-loop folder per
variant to ``--out``; a second call with the same ``--out`` skips what is done.
"""

import stride_jax
from stride_jax.jobs import dreamer_mpc

if __name__ == "__main__":
    stride_jax.set_xla_flags()  # before JAX starts: small CPUs deadlock without
    dreamer_mpc.main()
