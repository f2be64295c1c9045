"""Rollouts and the MPPI planner shard over devices: two forced host devices give the one-device
answer. (Training over two devices against one: ``test_distributed.py``.)

Two devices run in a subprocess, one in the test's own process (importing JAX and MJX is
most of a subprocess's cost)."""

import os
import pathlib
import subprocess
import sys

import numpy as np


def run(out: str, n: int) -> None:
    """Pendulum rollouts and three MPPI steps on ``n`` devices, saved in ``out``."""
    import jax
    import jax.numpy as jnp

    from stride_jax.control import mppi
    from stride_jax.sim import model, rollout_mjx
    assert len(jax.local_devices()) == n
    ep = rollout_mjx.collect(model.load("pendulum"), jax.random.key(0), 4, 20)
    np.save(out + "/q.npy", ep.records.q)

    def dynamics(q, qd, u, k):  # a stochastic double integrator, its samples split over devices
        qd = qd + 0.05 * (u + 0.1 * jax.random.normal(k, u.shape))
        return q + 0.05 * qd, qd

    cost = lambda q, qd, u, t: jnp.sum((q - 1.0) ** 2) + 0.01 * jnp.sum(u ** 2)
    cfg = mppi.MPPIConfig(samples=64, horizon=8, policy_samples=2)
    planner = mppi.make(cfg, dynamics, cost, -jnp.ones(2), jnp.ones(2), policy=lambda q, qd: -q,
                        sharding=mppi.sample_sharding())
    step = jax.jit(planner.step)
    state, q = planner.init(jax.random.key(0)), jnp.zeros(2)
    for _ in range(3):
        u, state, info = step(state, q, jnp.zeros(2))
    np.save(out + "/plan.npy", np.asarray(state.plan))


def test_rollouts_and_planning_on_two_devices_match_one(tmp_path):
    # two devices in a subprocess (a process's device count is fixed when JAX starts), one here
    env = dict(os.environ)
    env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "--xla_cpu_enable_concurrency_optimized_scheduler=false")
                        + " --xla_force_host_platform_device_count=2")  # conftest's flags too
    one, two = tmp_path / "dev1", tmp_path / "dev2"
    one.mkdir()
    two.mkdir()
    code = (f"import sys; sys.path.insert(0, {str(pathlib.Path(__file__).parent)!r}); "
            f"import test_sharding; test_sharding.run({str(two)!r}, 2)")
    proc = subprocess.Popen([sys.executable, "-c", code], env=env)
    run(str(one), 1)  # meanwhile: each is mostly single-threaded compilation
    assert proc.wait(timeout=600) == 0, f"subprocess exit code {proc.returncode}"
    np.testing.assert_allclose(np.load(two / "q.npy"), np.load(one / "q.npy"), atol=1e-6)
    plans = [np.load(o / "plan.npy") for o in (one, two)]
    assert np.abs(plans[0]).max() > 0.1  # the planner moved
    np.testing.assert_allclose(plans[1], plans[0], atol=1e-4)  # float rounding, 3 steps
