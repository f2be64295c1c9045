"""Process-level XLA settings that must be in place before JAX initialises.

``stride_jax/__init__.py`` imports this module first, so any ``import stride_jax`` before the first
``import jax`` is enough.
"""

import os

# On small CPUs, XLA's concurrency-optimised scheduler deadlocks inside the batched Cholesky that
# vmapped MJX steps use (batch >= 16 on a 2-core machine, reproduced with jax 0.10.2), and with
# that flag alone a training step of a Go1-sized structured model (128 x 3, batch 256) still hung
# after its first step in Eigen's thread pool (reproduced with jax 0.10.2 on 2 cores; single-
# threaded Eigen trains at 32 steps/s there). The user's own XLA_FLAGS win: we only add the flags
# when they set none.
CPU_SAFE_XLA_FLAGS = ("--xla_cpu_enable_concurrency_optimized_scheduler=false "
                      "--xla_cpu_multi_thread_eigen=false")

if "XLA_FLAGS" not in os.environ:
    os.environ["XLA_FLAGS"] = CPU_SAFE_XLA_FLAGS

# STRIDE_HOST_DEVICES=N (or "auto": one per core) splits the CPU into N XLA host devices, over which
# the MPPI planner shards its samples (``control.mppi.sample_sharding``): XLA runs one device's
# small operations one at a time, so on a small CPU this is what puts both cores to work.
_host_devices = os.environ.get("STRIDE_HOST_DEVICES", "")
if _host_devices and "xla_force_host_platform_device_count" not in os.environ["XLA_FLAGS"]:
    if _host_devices == "auto":
        _n = os.cpu_count() or 1
    elif _host_devices.isdigit() and int(_host_devices) > 0:
        _n = int(_host_devices)
    else:
        raise ValueError(f"STRIDE_HOST_DEVICES must be a positive integer or 'auto', got "
                         f"{_host_devices!r}")
    os.environ["XLA_FLAGS"] += f" --xla_force_host_platform_device_count={_n}"
