"""Shared fixtures. MJX compiles are the slow part of the suite: share them per session."""

import os
import pathlib

import pytest

import stride_jax

stride_jax.set_xla_flags()  # before JAX starts: the 2-core CPU deadlocks in XLA without

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


def _kernel_modes() -> list[str]:
    """The interpreter runs everywhere (CI); on a GPU the real Triton kernels run as well."""
    import jax
    return ["interpret"] + (["gpu"] if jax.default_backend() == "gpu" else [])


@pytest.fixture(params=_kernel_modes())
def kernels(request):
    """A context in which the fused kernels run as this test's mode asks: Pallas' interpreter,
    or (on a GPU) the compiled kernels."""
    import contextlib
    from stride_jax.dynamics import fused
    return fused.interpret if request.param == "interpret" else contextlib.nullcontext


def pytest_collection_modifyitems(config, items):
    """``gpu``-marked tests skip without a GPU, unless ``STRIDE_REQUIRE_GPU=1`` (``make
    test-gpu``), where a missing GPU is a failure rather than a skip."""
    import jax
    if jax.default_backend() == "gpu":
        return
    if os.environ.get("STRIDE_REQUIRE_GPU") == "1":
        raise pytest.UsageError(f"STRIDE_REQUIRE_GPU=1 but JAX runs on {jax.default_backend()}")
    skip = pytest.mark.skip(reason="needs a GPU (make test-gpu)")
    for item in items:
        if "gpu" in item.keywords:
            item.add_marker(skip)
