"""Side-by-side ``stride`` processes for the experiment drivers (``experiments/*.py``), and the
environment of CPU worker processes (the gap benchmark's process pool).

Small models leave a GPU idle between kernel launches, so the drivers train and evaluate several
runs at once as separate processes that share the device. A process that depends on another
(runs of one model whose seed-0 run fills JAX's persistent compilation cache first) waits until
its ``ready`` predicate holds.
"""

from __future__ import annotations

import os
import pathlib
import subprocess
import sys
import time
from typing import Callable, Mapping

from stride_jax import _env, config


def stride_command(*args: str) -> list[str]:
    """``python -m stride_jax.cli ARGS`` with this interpreter."""
    return [sys.executable, "-m", "stride_jax.cli", *args]


def shared_env(root: str | pathlib.Path) -> dict[str, str]:
    """This environment for processes sharing one device and ``<root>/.jax_cache``: no process
    takes most of the GPU's memory up front, and every compilation is cached for the others."""
    return dict(os.environ, XLA_PYTHON_CLIENT_PREALLOCATE="false",
                JAX_COMPILATION_CACHE_DIR=str((pathlib.Path(root) / ".jax_cache").absolute()),
                JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0",
                JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES="0")


def worker_env(env: Mapping[str, str], threads: int = 1) -> dict[str, str]:
    """``env`` for one of many CPU-bound worker processes on one machine: one thread each for XLA's
    Eigen kernels and BLAS/OpenMP, ``threads`` for the gap tool's MuJoCo rollouts
    (``STRIDE_GAP_THREADS``, the bulk of a diagnosis), so that N workers keep N x threads cores busy
    instead of N x cores threads contending for them.

    ``--xla_cpu_multi_thread_eigen`` is a flag of jaxlib 0.10 here and 0.11 on the lent machines
    (an unknown flag in ``XLA_FLAGS`` aborts the process). ``intra_op_parallelism_threads=1``, often
    quoted beside it, is TensorFlow's: XLA rejects it with dashes and silently ignores it without,
    so it is left out."""
    flags = env.get("XLA_FLAGS", _env.CPU_SAFE_XLA_FLAGS)
    if "xla_cpu_multi_thread_eigen" not in flags:
        flags = f"{flags} --xla_cpu_multi_thread_eigen=false".strip()
    return dict(env, XLA_FLAGS=flags, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1",
                STRIDE_GAP_THREADS=str(threads))


def set_env(env: Mapping[str, str]) -> None:
    """A process pool's ``initializer``: a spawned worker takes ``env`` before it first computes
    with JAX (XLA reads ``XLA_FLAGS`` when its backend starts, not at ``import jax``) or imports
    NumPy (BLAS reads its thread count when loaded)."""
    os.environ.update(env)


def config_flags(cfg) -> list[str]:
    """Every field of a config dataclass as ``stride`` flags (with ``--preset default``, the
    command rebuilds exactly ``cfg``)."""
    return ["--preset", "default", *config.to_flags(cfg)]


def run(cmds: dict[str, list[str]], logs: dict[str, pathlib.Path], parallel: int,
        env: dict | None = None, ready: dict[str, Callable[[], bool]] | None = None,
        t0: float | None = None, what: str = "job") -> list[str]:
    """Runs ``cmds`` (name -> argv), ``parallel`` at a time, each once ``ready[name]()`` holds
    (or once nothing else can run: a leader that failed must not block its followers), with
    output appended to ``logs[name]``. Prints one line per finished process; returns the names
    that failed."""
    ready, t0 = ready or {}, time.time() if t0 is None else t0
    pending, running, failed = list(cmds), [], []
    while pending or running:
        while len(running) < max(parallel, 1):
            eligible = [n for n in pending if ready.get(n, lambda: True)()]
            if not eligible and not running and pending:
                eligible = pending[:1]
            if not eligible:
                break
            name = eligible[0]
            pending.remove(name)
            logs[name].parent.mkdir(parents=True, exist_ok=True)
            log = open(logs[name], "a")
            proc = subprocess.Popen(cmds[name], stdout=log, stderr=subprocess.STDOUT, env=env)
            running.append((name, proc, log))
        time.sleep(1)
        for job in list(running):
            name, proc, log = job
            if proc.poll() is None:
                continue
            running.remove(job)
            log.close()
            if proc.returncode:
                failed.append(name)
            status = "ok" if proc.returncode == 0 else f"FAILED ({proc.returncode})"
            print(f"[{time.time() - t0:.0f} s] {what} {name}: {status}", flush=True)
    return failed
