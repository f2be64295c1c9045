"""``stride bench-sim``'s measurement at tiny size: MJX's physics and collection rows (the latter
the device-side call of ``stride data``'s collection), and clear errors for bad settings."""

import math

import pytest

from stride_jax.jobs import bench_sim
from stride_jax.sim import model


def test_mjx_rows_measure_physics_and_the_collection_call():
    cfg = bench_sim.BenchConfig(robots="pendulum", backends="mjx", batches="4", steps=3,
                                repeats=1)
    rows = bench_sim.measure(cfg)
    assert [(r["mode"], r["batch"]) for r in rows] == [("physics", 4), ("collect", 4)]
    assert all(math.isfinite(r["steps_per_s"]) and r["steps_per_s"] > 0 for r in rows)
    substeps = model.load("pendulum").n_substeps
    assert all(r["sim_steps"] == 4 * 3 * substeps for r in rows)


@pytest.mark.parametrize("change, says", [(dict(split="pmap"), "split='pmap'"),
                                          (dict(backends="gpu"), "unknown backends")])
def test_bad_settings_are_clear_errors(change, says):
    cfg = bench_sim.BenchConfig(robots="pendulum", batches="4", steps=3, repeats=1, **change)
    with pytest.raises(ValueError, match=says):
        bench_sim.measure(cfg)
