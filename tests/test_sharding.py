"""Rollouts shard over devices: two forced host devices give the single-device answer."""

import os
import subprocess
import sys

import numpy as np

SCRIPT = """
import stride_jax, jax, numpy as np, sys
from stride_jax.sim import model, rollout_mjx
assert len(jax.local_devices()) == int(sys.argv[2])
ep = rollout_mjx.collect(model.load('pendulum'), jax.random.key(0), 4, 20)
np.save(sys.argv[1], ep.records.q)
"""


def _run(tmp_path, n_devices):
    env = dict(os.environ)
    env["XLA_FLAGS"] = ("--xla_cpu_enable_concurrency_optimized_scheduler=false "
                        f"--xla_force_host_platform_device_count={n_devices}")
    out = tmp_path / f"q{n_devices}.npy"
    subprocess.run([sys.executable, "-c", SCRIPT, str(out), str(n_devices)], check=True, env=env)
    return np.load(out)


def test_two_devices_match_one(tmp_path):
    np.testing.assert_allclose(_run(tmp_path, 2), _run(tmp_path, 1), atol=1e-6)
