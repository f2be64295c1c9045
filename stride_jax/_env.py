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
# JAX's persistent compilation cache for the entry points: a second `stride train` (or closed
# loop, benchmark, experiment) with the same shapes loads its programs instead of compiling them
# (on 2 CPU cores: the pendulum's default training 25.6 s -> 19.5 s of wall time, Go1's tiny one
# 19.9 s -> 10.8 s, commands in the README; on an H200 a 6000-step Go1 run spent about 23 s of its
# 50 s compiling, results/throughput/README.md, session 73). JAX keeps only programs that took 1 s
# to compile by default, none of the pendulum's: programs of 0.1 s and more are kept here (13 files, 0.6 MB
# for the pendulum; all of them, 0.1 s more saved, were 97 files); the folder is bounded, JAX
# evicting the least recently used entries beyond it (with the `filelock` package).
CACHE_ENV = "STRIDE_JAX_CACHE"
CACHE_MAX_BYTES = 2 << 30
CACHE_MIN_COMPILE_S = 0.1
# With several XLA host devices, two devices' programs can each hold one of XLA's CPU pool
# threads inside a batched LAPACK Cholesky (MJX's solver) that waits for its share of the batch
# to run on that same pool; with the pool's default of one thread per core both wait for ever
# (reproduced with jax 0.10.2 on 2 cores: G1 MJX collection on two host devices hung in both of
# ``rollout_mjx.collect``'s splits, as did ``stride bench-mppi``'s G1 oracle with its samples
# split; Go1's smaller systems stay below LAPACK's split). XLA sizes that pool from ``NPROC``.
# A larger pool is not the default: on two host devices of 2 cores it slowed the learned models'
# MPPI step by 24-28% (Go1 STRIDE 256 x 3, K=128, H=16: 32.4 -> 41.6 ms with NPROC=4, 35.3 ->
# 43.6 with 6) and Go1 MJX collection by ~14% (NPROC 3-6). So MJX work keeps to one host device
# unless the process sets ``NPROC`` to at least :func:`pool_needed`.
POOL_ENV = "NPROC"


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

    Also turns on JAX's persistent compilation cache in :func:`compilation_cache_dir` (unless
    the process set ``JAX_COMPILATION_CACHE_DIR`` itself, which wins): see :data:`CACHE_ENV`.
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
    _use_compilation_cache()
    if os.environ["XLA_FLAGS"] != before and _backend_started():
        warnings.warn("stride_jax.set_xla_flags() ran after JAX's backend started: XLA_FLAGS "
                      "take effect in child processes only; call it before the first JAX "
                      "computation", stacklevel=2)


def pool_needed(devices: int) -> int:
    """XLA's CPU pool (``NPROC``) that lets ``devices`` host devices each hold a thread in a
    batched LAPACK call while the cores' threads run its parts (:data:`POOL_ENV`)."""
    return (os.cpu_count() or 1) + devices


_POOL_WARNED: set = set()


def side_by_side_lapack(devices: list) -> list:
    """Of ``devices``, those that may run batched LAPACK calls (MJX's solver) side by side: all
    of them, unless they are several host devices of a CPU whose XLA pool is smaller than
    :func:`pool_needed` (they would hang, :data:`POOL_ENV`): then the first, with a warning."""
    if len(devices) < 2 or devices[0].platform != "cpu":
        return devices
    pool = os.environ.get(POOL_ENV, "")
    pool = int(pool) if pool.isdigit() else (os.cpu_count() or 1)
    need = pool_needed(len(devices))
    if pool >= need:
        return devices
    if len(devices) not in _POOL_WARNED:
        _POOL_WARNED.add(len(devices))
        warnings.warn(f"MJX runs on one of the {len(devices)} XLA host devices: side by side, "
                      f"their batched LAPACK calls can hang XLA's CPU pool of {pool} threads; "
                      f"set {POOL_ENV}={need} before JAX starts to use them all "
                      f"(stride_jax/_env.py, POOL_ENV)", stacklevel=3)
    return devices[:1]


def compilation_cache_dir() -> str | None:
    """Where the entry points keep compiled programs between processes: ``STRIDE_JAX_CACHE`` (a
    folder; ``0``, ``off`` or empty: none), else ``$XDG_CACHE_HOME/stride_jax/jax``
    (``~/.cache/stride_jax/jax``). A ``JAX_COMPILATION_CACHE_DIR`` of the process's own is used
    as it is and this is not consulted."""
    value = os.environ.get(CACHE_ENV)
    if value is not None:
        return None if value.strip().lower() in ("", "0", "off", "none", "false") else value
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "stride_jax", "jax")


def _use_compilation_cache() -> None:
    """Points JAX's persistent compilation cache at :func:`compilation_cache_dir` (the
    environment for child processes and a JAX not imported yet, JAX's config for one already
    imported), bounded to :data:`CACHE_MAX_BYTES`; nothing where the process chose its own
    folder or turned it off."""
    if os.environ.get("JAX_COMPILATION_CACHE_DIR"):
        return
    folder = compilation_cache_dir()
    if folder is None:
        return
    try:
        os.makedirs(folder, exist_ok=True)
        if not os.access(folder, os.W_OK):
            raise PermissionError("not writable")
    except OSError as e:  # one clear warning instead of JAX's per program, and no cache
        warnings.warn(f"stride_jax: no compilation cache, the folder {folder} cannot be used ({e}); "
                      f"set {CACHE_ENV} to a writable folder, or to 0 to turn the cache off", stacklevel=3)
        return
    settings = {"JAX_COMPILATION_CACHE_DIR": folder,
                "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": str(CACHE_MIN_COMPILE_S)}
    try:  # without it JAX fails to open a bounded cache, silently: unbounded then
        import filelock  # noqa: F401
        settings["JAX_COMPILATION_CACHE_MAX_SIZE"] = str(CACHE_MAX_BYTES)
    except ImportError:
        pass
    for name, value in settings.items():
        os.environ.setdefault(name, value)  # the process's own settings of the others win
    if "jax" in sys.modules:  # read at its import: a JAX imported already is told directly
        import jax
        jax.config.update("jax_compilation_cache_dir", folder)
        jax.config.update("jax_persistent_cache_min_compile_time_secs",
                          float(os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"]))
        if "JAX_COMPILATION_CACHE_MAX_SIZE" in os.environ:
            jax.config.update("jax_compilation_cache_max_size", int(os.environ["JAX_COMPILATION_CACHE_MAX_SIZE"]))


def _backend_started() -> bool:
    if "jax" not in sys.modules:
        return False
    try:
        from jax._src import xla_bridge
        return bool(xla_bridge.backends_are_initialized())
    except (ImportError, AttributeError):  # a JAX without the (private) query: cannot tell
        return False
