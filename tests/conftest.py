"""Shared fixtures. MJX compiles are the slow part of the suite: share them per session."""

import atexit
import os
import pathlib
import shutil
import tempfile

# Many tests compile the same programs through new closures (a model rebuilt, a rollout function
# made again), which JAX's in-memory cache does not see: a persistent compilation cache for the
# session (and the subprocesses it starts) compiles each program once. Set before JAX imports.
if "JAX_COMPILATION_CACHE_DIR" not in os.environ:
    _cache = tempfile.mkdtemp(prefix="stride-jax-test-cache-")
    atexit.register(shutil.rmtree, _cache, ignore_errors=True)
    os.environ["JAX_COMPILATION_CACHE_DIR"] = _cache
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.5")
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES", "0")

import stride_jax  # noqa: E402, F401  (XLA flags before JAX initialises)

import pytest

SHARED = pathlib.Path(__file__).resolve().parents[1].parent / "shared" / "menagerie"
if "MENAGERIE_ROOT" not in os.environ and SHARED.is_dir():
    os.environ["MENAGERIE_ROOT"] = str(SHARED)


@pytest.fixture(scope="session")
def go1():
    from stride_jax.sim import model
    return model.load("go1")


@pytest.fixture(scope="session")
def g1():
    from stride_jax.sim import model
    return model.load("g1")
