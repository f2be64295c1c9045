"""Shared fixtures. MJX compiles are the slow part of the suite: share them per session."""

import os
import pathlib
import sys

import pytest

import stride_jax

# Tests compile far more than they compute (three MJX-heavy files: 99 s with a warm compilation
# cache, 281 s cold), so off a GPU run they take XLA's LLVM optimisation off, beside the CPU-safe
# flags; only where the user set no XLA_FLAGS. Measured by clean-clone .ci/run on 2 cores, same
# day, same split: workers 16.9 / 19.3 and 16.5 / 18.3 min with it (7072ba1, 91ab006), 21.7 / 23.3
# without (8b5ecd2).
# XLA:CPU's new fusion emitters and LLVM's expensive passes off as well: compile time is most of
# the suite's (test_record.py: 66 of 93 s in XLA's backend compile, 19 in tracing), and without
# them test_models.py took 54 s instead of 83, test_record.py 46 instead of 56 (quiet 2-core
# machine, one process each, same day).
TEST_XLA_FLAGS = (" --xla_backend_optimization_level=0 --xla_cpu_use_fusion_emitters=false"
                  " --xla_llvm_disable_expensive_passes=true")
if "XLA_FLAGS" not in os.environ and os.environ.get("STRIDE_REQUIRE_GPU") != "1":
    os.environ["XLA_FLAGS"] = stride_jax.CPU_SAFE_XLA_FLAGS + TEST_XLA_FLAGS
stride_jax.set_xla_flags()  # before JAX starts: the 2-core CPU deadlocks in XLA without

SHARED = pathlib.Path(__file__).resolve().parents[1].parent / "shared" / "menagerie"
if "MENAGERIE_ROOT" not in os.environ and SHARED.is_dir():
    os.environ["MENAGERIE_ROOT"] = str(SHARED)


@pytest.fixture(autouse=True)
def _fresh_replay_memo():
    """Each test starts with the gap tool's replay memo empty (:mod:`stride_jax.gap.memo`): a test
    that patches how replays run must not be handed another test's results."""
    memo = sys.modules.get("stride_jax.gap.memo")
    if memo is not None:
        memo.clear()
    yield


@pytest.fixture(scope="session")
def run_time_bound() -> dict:
    """``compiler_options`` for a ``jax.jit`` whose run time, not its compile time, dominates (a
    training step taken thousands of times): optimisation level 2 over the suite's O0 flags
    (above). test_stride's fixture 37 -> 17 s, test_networks' two generators 13 -> 8 s (session
    58, this 2-core host)."""
    return {"xla_backend_optimization_level": 2}


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


_ARM_MJCF = """
<mujoco model="arm">
  <option timestep="0.002"/>
  <worldbody>
    <body name="upper" pos="0 0 1">
      <joint name="shoulder" type="hinge" axis="0 1 0" range="-2 2" damping="0.05"/>
      <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03" mass="1"/>
      <body name="fore" pos="0.3 0 0">
        <joint name="elbow" type="hinge" axis="0 1 0" range="-2 2" damping="0.05"/>
        <geom type="capsule" fromto="0 0 0 0.25 0 0" size="0.025" mass="0.5"/>HAND
      </body>
    </body>
  </worldbody>ACTUATORS
</mujoco>
"""
_HAND = """
        <body name="hand" pos="0.25 0 0">
          <joint name="wrist" type="hinge" axis="0 1 0"/>
          <geom type="sphere" size="0.03" mass="0.2"/>
        </body>"""


def write_arm(folder: pathlib.Path, actuators: str = "", name: str = "arm.xml",
              hand: bool = False) -> pathlib.Path:
    """A two-link arm's MJCF (shoulder and elbow hinges, damped and limited; ``hand``: a third,
    free wrist hinge with a payload) in ``folder/name``, with ``actuators`` (an ``<actuator>``
    block) or none; returns its path. The robot takes its name from the file's stem."""
    path = pathlib.Path(folder) / name
    path.write_text(_ARM_MJCF.replace("HAND", _HAND if hand else "")
                    .replace("ACTUATORS", "\n  " + actuators if actuators else ""))
    return path


@pytest.fixture(scope="session")
def arm_mjcf():
    """:func:`write_arm`, the one arm the robot-file and log-import tests share."""
    return write_arm


def _load_experiment(name: str):
    """The script ``experiments/<name>.py`` as a module (the scripts are not a package)."""
    import importlib.util
    path = pathlib.Path(__file__).resolve().parents[1] / "experiments" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(f"experiment_{name}", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up while the script runs
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="session")
def experiment():
    """``experiment(name)``: the script ``experiments/<name>.py`` as a module."""
    return _load_experiment
