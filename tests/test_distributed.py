"""Several processes, one job (stride_jax.distributed): two processes on this CPU make the dataset
one process makes, byte for byte, and train the model one process trains, up to the order of the
gradients' summation."""

import json
import os
import pathlib
import socket
import subprocess
import sys

import jax
import numpy as np
import pytest

from stride_jax import distributed
from stride_jax import dynamics


def _port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def _stride(args: list[str], log: pathlib.Path, devices: int = 1) -> subprocess.Popen:
    # Output to a file, not a pipe: a process blocked on a full pipe would stall the other's
    # collectives.
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    if devices > 1:  # forced host devices: one process, several local devices
        env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "") +
                            f" --xla_force_host_platform_device_count={devices}").strip()
    with open(log, "w") as f:
        return subprocess.Popen([sys.executable, "-m", "stride_jax.cli", *args], stdout=f,
                                stderr=subprocess.STDOUT, env=env)


def _wait(procs: list[subprocess.Popen], logs: list[pathlib.Path]) -> None:
    for p, log in zip(procs, logs):
        p.wait(timeout=600)
        assert p.returncode == 0, log.read_text()[-3000:]


def _together(args: list[str], tmp: pathlib.Path) -> None:
    """``stride ARGS`` as a job of two processes on this machine."""
    port = _port()
    logs = [tmp / f"{args[0]}-{i}.log" for i in (0, 1)]
    _wait([_stride([*args, "--distributed.coordinator", f"localhost:{port}",
                    "--distributed.num-processes", "2", "--distributed.process-id", str(i)],
                   log) for i, log in enumerate(logs)], logs)


def _alone(args: list[str], tmp: pathlib.Path, devices: int = 1) -> None:
    log = tmp / f"{args[0]}-{devices}dev.log"
    _wait([_stride(args, log, devices)], [log])


DATA = ["data", "--robot", "pendulum", "--preset", "tiny"]
TRAIN = ["train", "--robot", "pendulum", "--model", "stride", "--preset", "tiny", "--steps", "30"]


@pytest.fixture(scope="module")
def alone(tmp_path_factory) -> pathlib.Path:
    """The dataset (``d1``) and the model (``r1``) of one process with one device: the reference
    both tests below compare with (made once, in this process: a ``stride`` process costs ~7 s
    of imports before its job starts)."""
    from stride_jax import cli

    tmp = tmp_path_factory.mktemp("alone")
    cli.main([*DATA, "--out", str(tmp / "d1")])
    cli.main([*TRAIN, "--data", str(tmp / "d1"), "--out", str(tmp / "r1")])
    return tmp


def _same_model(r1: pathlib.Path, r2: pathlib.Path) -> None:
    (_, p1), (_, p2) = dynamics.load(r1), dynamics.load(r2)
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-3, atol=1e-5), p1, p2)
    s1, s2 = (json.loads((r / "summary.json").read_text()) for r in (r1, r2))
    assert s1["best_step"] == s2["best_step"] == 30
    assert s2["best_val"] == pytest.approx(s1["best_val"], rel=1e-4)


@pytest.mark.slow  # one process with two devices: the test below
def test_two_processes_make_the_same_dataset_and_model(alone, tmp_path):
    _together([*DATA, "--out", str(tmp_path / "d2")], tmp_path)
    meta = [json.loads((d / "meta.json").read_text()) for d in (alone / "d1", tmp_path / "d2")]
    assert meta[0]["arrays_sha256"] == meta[1]["arrays_sha256"]
    _together([*TRAIN, "--data", str(alone / "d1"), "--out", str(tmp_path / "r2")], tmp_path)
    _same_model(alone / "r1", tmp_path / "r2")


def test_settings_come_from_flags_or_the_environment():
    none = distributed.DistributedConfig()
    assert distributed.resolve(none, {}) is None  # a single process
    env = {"STRIDE_COORDINATOR": "node0:1234", "STRIDE_NUM_PROCESSES": "4",
           "STRIDE_PROCESS_ID": "3"}
    assert distributed.resolve(none, env) == distributed.DistributedConfig("node0:1234", 4, 3)
    flags = distributed.DistributedConfig("node1:99", 2, 0)
    assert distributed.resolve(flags, env) == flags  # flags win
    assert distributed.resolve(distributed.DistributedConfig("auto"), {}).coordinator == "auto"
    with pytest.raises(ValueError, match="process_id"):
        distributed.resolve(distributed.DistributedConfig("node0:1", 2, 2), {})
    with pytest.raises(ValueError, match="num_processes"):
        distributed.resolve(distributed.DistributedConfig("node0:1"), {})


def test_one_process_with_two_devices_trains_the_same_model(alone, tmp_path):
    """Two local devices of one process (the minibatch split over them, data and parameters
    replicated on each): the model one device trains, up to the order of the gradients'
    summation, and a checkpoint that restores in a one-device process."""
    _alone([*TRAIN, "--data", str(alone / "d1"), "--out", str(tmp_path / "r2")], tmp_path, devices=2)
    _same_model(alone / "r1", tmp_path / "r2")


def test_seeds_side_by_side_split_over_two_devices(alone, tmp_path):
    """``stride train --seeds 0,1`` in one process with two local devices: a seed on each, and
    seed 0's run is the model one device trains alone with seed 0 (to float rounding)."""
    _alone([*TRAIN, "--data", str(alone / "d1"), "--out", str(tmp_path / "r"), "--seeds", "0,1"], tmp_path,
           devices=2)
    assert "2 runs side by side over 2 devices, 1 each" in (tmp_path / "train-2dev.log").read_text()
    _same_model(alone / "r1", tmp_path / "r-s0")
