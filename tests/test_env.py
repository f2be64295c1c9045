"""Process-level settings read before JAX starts (``stride_jax/_env.py``)."""

import os
import subprocess
import sys

import pytest

PROBE = "import stride_jax, jax, os; print(len(jax.devices()), os.environ['XLA_FLAGS'])"


def _run(**env):
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "STRIDE_HOST_DEVICES")
           } | env
    return subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True, text=True)


@pytest.mark.parametrize("value, devices", [("2", 2), ("auto", os.cpu_count() or 1)])
def test_host_devices_split_the_cpu(value, devices):
    out = _run(STRIDE_HOST_DEVICES=value)
    assert out.returncode == 0, out.stderr
    n, flags = out.stdout.split(" ", 1)
    assert int(n) == devices
    assert "concurrency_optimized_scheduler=false" in flags  # the deadlock guards stay
    assert "multi_thread_eigen=false" in flags


def test_bad_host_device_count_is_a_clear_error():
    out = _run(STRIDE_HOST_DEVICES="two")
    assert out.returncode != 0 and "STRIDE_HOST_DEVICES must be a positive integer" in out.stderr
