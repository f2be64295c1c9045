"""Rollouts and training shard over devices: two forced host devices give the one-device answer."""

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


TRAIN_SCRIPT = """
import stride_jax, jax, numpy as np, sys
from stride_jax import cli
from stride_jax.dynamics import models
assert len(jax.local_devices()) == int(sys.argv[3])
cli.main(["train", "--robot", "pendulum", "--preset", "tiny", "--steps", "20", "--batch", "64",
          "--eval-every", "10", "--data", sys.argv[2], "--out", sys.argv[1] + "/run"])
_, params = models.load(sys.argv[1] + "/run")
np.save(sys.argv[1] + "/params.npy", np.concatenate([np.ravel(x) for x in jax.tree.leaves(params)]))
"""


def test_training_on_two_devices_matches_one(tmp_path):
    from stride_jax import cli
    data = tmp_path / "data"
    cli.main(["data", "--robot", "pendulum", "--preset", "tiny", "--out", str(data)])
    params = []
    for n in (1, 2):
        env = dict(os.environ)
        env["XLA_FLAGS"] = ("--xla_cpu_enable_concurrency_optimized_scheduler=false "
                            f"--xla_force_host_platform_device_count={n}")
        out = tmp_path / f"dev{n}"
        out.mkdir()
        subprocess.run([sys.executable, "-c", TRAIN_SCRIPT, str(out), str(data), str(n)],
                       check=True, env=env)
        params.append(np.load(out / "params.npy"))
    assert np.abs(params[0]).max() > 0
    np.testing.assert_allclose(params[1], params[0], atol=1e-5, rtol=1e-4)
