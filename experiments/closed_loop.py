"""Closed-loop MPPI on the MJX Go1 (issue 4): tracking error and falls per dynamics model on the
velocity step, sudden command changes, a 20 degree slope and unseen ground.

    python experiments/closed_loop.py --preset tiny                      # CPU, seconds
    python experiments/closed_loop.py --preset gpu --policy runs/ppo_go1 --policy-samples 64 \\
        --models oracle,nominal,policy,stride=runs/go1/stride,delan=runs/go1/delan

Writes ``closed_loop.json``/``.md``, traces and one plot per scenario to ``--out``; a second call
with the same ``--out`` skips the (scenario, model) pairs already there.
"""

import stride_jax
from stride_jax.jobs import closed_loop

if __name__ == "__main__":
    stride_jax.set_xla_flags()  # before JAX starts: small CPUs deadlock without
    closed_loop.main()
