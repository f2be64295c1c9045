"""Process-level settings read before JAX starts (``stride_jax/_env.py``): set by the entry
points through ``stride_jax.set_xla_flags``, never by importing the package."""

import os
import subprocess
import sys

import pytest

PROBE = ("import stride_jax, jax, os; stride_jax.set_xla_flags(); "
         "print(len(jax.devices()), os.environ['XLA_FLAGS'])")


def _run(probe=PROBE, *args, timeout=None, **env):
    drop = ("XLA_FLAGS", "STRIDE_HOST_DEVICES", "STRIDE_DETERMINISTIC", "NPROC")
    env = {k: v for k, v in os.environ.items() if k not in drop} | env
    return subprocess.run([sys.executable, "-c", probe, *args], env=env, capture_output=True,
                          text=True, timeout=timeout)


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


def test_importing_sets_nothing_and_the_order_does_not_matter():
    """A user's process keeps its environment on ``import stride_jax`` (with any import order);
    the user's own flags win over the helper's; a call after JAX started warns."""
    probe = ("import jax, stride_jax, stride_jax.dynamics, os; "
             "print(os.environ.get('XLA_FLAGS'))")
    out = _run(probe)
    assert out.returncode == 0 and out.stdout.strip() == "None", out.stderr
    out = _run(PROBE, XLA_FLAGS="--xla_dump_to=/dev/null")
    assert out.returncode == 0, out.stderr
    assert out.stdout.split(" ", 1)[1].strip() == "--xla_dump_to=/dev/null"
    late = ("import warnings, jax, stride_jax; jax.devices(); warnings.simplefilter('error'); "
            "stride_jax.set_xla_flags()")
    out = _run(late)
    assert out.returncode != 0 and "after JAX's backend started" in out.stderr


def test_the_command_line_sets_the_flags():
    """``stride --help`` sets the flags and lists every subcommand without importing a job (or
    JAX: it took 8 s on 2 cores when it imported them all); a subcommand imports its own job."""
    probe = ("import os, sys; from stride_jax import cli; sys.argv = ['stride'] + sys.argv[1:]\n"
             "try:\n    cli.main()\nexcept SystemExit:\n    pass\n"
             "print(sorted(m for m in sys.modules if m.startswith('stride_jax.jobs.') or m == 'jax'))\n"
             "print(os.environ['XLA_FLAGS'])")
    out = _run(probe, "--help")
    assert out.returncode == 0, out.stderr
    assert "multi_thread_eigen=false" in out.stdout.splitlines()[-1]
    assert out.stdout.splitlines()[-2] == "[]"
    from stride_jax import cli
    assert all(name in out.stdout for name in cli.COMMANDS)
    out = _run(probe, "show", "--help")
    assert out.returncode == 0, out.stderr
    assert "--stride" in out.stdout and "stride_jax.jobs.show" in out.stdout.splitlines()[-2]


def test_importing_any_module_leaves_jax_unstarted():
    """XLA reads its flags when its backend starts: no module may start it at import (a
    module-level jnp array did, so `python -m stride_jax.control.closed_loop` -- now
    `stride_jax.jobs.closed_loop` -- set them too late)."""
    code = ("import importlib, pkgutil, stride_jax, stride_paper\n"
            "from jax._src import xla_bridge\n"
            "for pkg in (stride_jax, stride_paper):\n"
            "    for m in pkgutil.walk_packages(pkg.__path__, pkg.__name__ + '.'):\n"
            "        importlib.import_module(m.name)\n"
            "        assert not xla_bridge.backends_are_initialized(), m.name\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=300, env={**os.environ, "JAX_PLATFORMS": "cpu"})
    assert out.returncode == 0, out.stderr[-2000:]


def test_the_data_job_asks_for_deterministic_gpu_ops():
    """``stride data`` adds XLA's deterministic-ops flag (a GPU simulated the same seed twice into
    different datasets without it); without the request, with the opt-out or with the user's own
    flag it is not added."""
    probe = ("import os, sys; from stride_jax import cli; sys.argv = ['stride', 'data', '--help']\n"
             "try:\n    cli.main()\nexcept SystemExit:\n    pass\n"
             "print(os.environ['XLA_FLAGS'])")
    out = _run(probe)
    assert out.returncode == 0, out.stderr
    flags = out.stdout.splitlines()[-1]
    assert "--xla_gpu_deterministic_ops=true" in flags
    assert "multi_thread_eigen=false" in flags  # the CPU guards stay
    asked = ("import os, stride_jax; stride_jax.set_xla_flags(deterministic={}); "
             "print(os.environ['XLA_FLAGS'])")
    assert "deterministic" not in _run(asked.format(False)).stdout
    assert "deterministic" not in _run(asked.format(True), STRIDE_DETERMINISTIC="0").stdout
    user = _run(asked.format(True), XLA_FLAGS="--xla_gpu_deterministic_ops=false").stdout
    assert user.strip() == "--xla_gpu_deterministic_ops=false"


def test_the_entry_points_keep_compiled_programs_between_processes(tmp_path):
    """``set_xla_flags`` turns JAX's persistent compilation cache on in the user's cache folder
    (``$XDG_CACHE_HOME/stride_jax/jax``): a compiled program lands there, bounded in size; a
    ``STRIDE_JAX_CACHE`` folder replaces it, ``STRIDE_JAX_CACHE=0`` turns it off, and the
    process's own ``JAX_COMPILATION_CACHE_DIR`` wins."""
    probe = ("import stride_jax, jax, jax.numpy as jnp, os; stride_jax.set_xla_flags(); "
             "jax.jit(lambda x: jnp.sin(x) @ x.T)(jnp.ones((8, 8))).block_until_ready(); "
             "print(jax.config.jax_compilation_cache_dir, jax.config.jax_compilation_cache_max_size)")
    drop = ("JAX_COMPILATION_CACHE_DIR", "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS",
            "JAX_COMPILATION_CACHE_MAX_SIZE", "STRIDE_JAX_CACHE")
    base = {k: v for k, v in os.environ.items() if k not in drop}
    base |= {"XDG_CACHE_HOME": str(tmp_path / "xdg"), "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0"}

    def run(**env):
        out = subprocess.run([sys.executable, "-c", probe], env=base | env, capture_output=True, text=True)
        assert out.returncode == 0, out.stderr
        return out.stdout.split()

    folder, size = run()
    assert folder == str(tmp_path / "xdg" / "stride_jax" / "jax") and int(size) > 0
    assert any(p.is_file() for p in (tmp_path / "xdg" / "stride_jax" / "jax").rglob("*"))
    assert run(STRIDE_JAX_CACHE=str(tmp_path / "mine"))[0] == str(tmp_path / "mine")
    assert any((tmp_path / "mine").rglob("*"))
    assert run(STRIDE_JAX_CACHE="0")[0] == "None"
    (tmp_path / "file").write_text("")
    out = subprocess.run([sys.executable, "-c", probe], env=base | {"STRIDE_JAX_CACHE": str(tmp_path / "file")},
                         capture_output=True, text=True)
    assert out.returncode == 0 and out.stdout.split()[0] == "None", out.stderr
    assert out.stderr.count("no compilation cache, the folder") == 1 and "STRIDE_JAX_CACHE" in out.stderr
    assert run(JAX_COMPILATION_CACHE_DIR=str(tmp_path / "theirs"))[0] == str(tmp_path / "theirs")


CHOLESKY_ON_TWO_DEVICES = """
import stride_jax; stride_jax.set_xla_flags()
import os, warnings, jax, jax.numpy as jnp
from stride_jax.sim import rollout_mjx
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    devices = rollout_mjx.mjx_devices()
a = jax.random.normal(jax.random.key(0), (256, 48, 48))
a = a @ jnp.swapaxes(a, 1, 2) + 48 * jnp.eye(48)
f = jax.jit(lambda x: jnp.linalg.cholesky(x).sum())
xs = [jax.device_put(a, d) for d in devices]
for _ in range(200):  # the devices' batched LAPACK Choleskys at once, as MJX's solver on G1
    jax.block_until_ready([f(x) for x in xs])
print(len(jax.devices()), len(devices), "NPROC" in "".join(str(w.message) for w in caught))
"""


@pytest.mark.parametrize("pool, uses, warns", [("", 1, True), ("pool_needed", 2, False)])
def test_mjx_keeps_to_host_devices_whose_batched_choleskys_cannot_hang(pool, uses, warns):
    """Two host devices running batched LAPACK Choleskys side by side hung on 2 cores with XLA's
    default pool (each device's program held a pool thread waiting for the other half of its
    batch): MJX keeps to one of them and says how to use both (``_env.POOL_ENV``); with that
    pool both run side by side and finish."""
    from stride_jax import _env

    env = dict(STRIDE_HOST_DEVICES="2") | (dict(NPROC=str(_env.pool_needed(2))) if pool else {})
    try:
        out = _run(CHOLESKY_ON_TWO_DEVICES, timeout=120, **env)
    except subprocess.TimeoutExpired:
        pytest.fail("two host devices' batched Choleskys hung (XLA's CPU pool too small)")
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["2", str(uses), str(warns)]
