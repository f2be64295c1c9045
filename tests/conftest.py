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
