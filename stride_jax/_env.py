"""Process-level XLA settings that must be in place before JAX initialises its backend.

Importing ``stride_jax`` changes nothing in a user's process. The entry points (the ``stride``
command, ``python -m`` modules, ``experiments/*.py``, the test suite) call
:func:`set_xla_flags` first; a user's own script on a small CPU does the same::

    import stride_jax
    stride_jax.set_xla_flags()   # before the first JAX computation

XLA reads ``XLA_FLAGS`` when its backend starts (the first computation or device query), not at
``import jax``, so the call works anywhere before that.
"""

import os
import sys
import warnings

# On small CPUs, XLA's concurrency-optimised scheduler deadlocks inside the batched Cholesky that
# vmapped MJX steps use (batch >= 16 on a 2-core machine, reproduced with jax 0.10.2), and with
# that flag alone a training step of a Go1-sized structured model (128 x 3, batch 256) still hung
# after its first step in Eigen's thread pool (reproduced with jax 0.10.2 on 2 cores; single-
# threaded Eigen trains at 32 steps/s there). The user's own XLA_FLAGS win: we only add the flags
# when they set none.
CPU_SAFE_XLA_FLAGS = ("--xla_cpu_enable_concurrency_optimized_scheduler=false "
                      "--xla_cpu_multi_thread_eigen=false")
# On a GPU, XLA's scatter-adds (MJX assembles its constraints with them) and its autotuned kernel
# choices vary from run to run, so a dataset simulated twice from one seed came out different
# (Table I's G1 and Go1 walking data, regenerated on the same kind of H200: other sha256). The
# data job asks for deterministic ops (``STRIDE_DETERMINISTIC=0`` opts out).
GPU_DETERMINISTIC_FLAG = "--xla_gpu_deterministic_ops=true"


def set_xla_flags(deterministic: bool = False) -> None:
    """Sets ``XLA_FLAGS`` to :data:`CPU_SAFE_XLA_FLAGS` unless the process (user) set any, and
    splits the CPU into ``STRIDE_HOST_DEVICES`` XLA host devices where that is set. Idempotent;
    child processes inherit the setting. Warns if JAX's backend already started (too late).

    ``deterministic``: also :data:`GPU_DETERMINISTIC_FLAG` (run-to-run identical results on a
    GPU; no effect on a CPU), unless the flags name it already or ``STRIDE_DETERMINISTIC=0``.

    ``STRIDE_HOST_DEVICES=N`` (or ``auto``: one per core) splits the CPU into N XLA host
    devices, over which the MPPI planner shards its samples (``control.mppi.sample_sharding``):
    XLA runs one device's small operations one at a time, so on a small CPU this is what puts
    both cores to work.
    """
    before = os.environ.get("XLA_FLAGS")
    if before is None:
        os.environ["XLA_FLAGS"] = CPU_SAFE_XLA_FLAGS
    host_devices = os.environ.get("STRIDE_HOST_DEVICES", "")
    if host_devices and "xla_force_host_platform_device_count" not in os.environ["XLA_FLAGS"]:
        if host_devices == "auto":
            n = os.cpu_count() or 1
        elif host_devices.isdigit() and int(host_devices) > 0:
            n = int(host_devices)
        else:
            raise ValueError(f"STRIDE_HOST_DEVICES must be a positive integer or 'auto', got "
                             f"{host_devices!r}")
        os.environ["XLA_FLAGS"] += f" --xla_force_host_platform_device_count={n}"
    if (deterministic and os.environ.get("STRIDE_DETERMINISTIC", "1") != "0"
            and "xla_gpu_deterministic_ops" not in os.environ["XLA_FLAGS"]):
        os.environ["XLA_FLAGS"] += " " + GPU_DETERMINISTIC_FLAG
    if os.environ["XLA_FLAGS"] != before and _backend_started():
        warnings.warn("stride_jax.set_xla_flags() ran after JAX's backend started: XLA_FLAGS "
                      "take effect in child processes only; call it before the first JAX "
                      "computation", stacklevel=2)


def _backend_started() -> bool:
    if "jax" not in sys.modules:
        return False
    try:
        from jax._src import xla_bridge
        return bool(xla_bridge.backends_are_initialized())
    except (ImportError, AttributeError):  # a JAX without the (private) query: cannot tell
        return False
