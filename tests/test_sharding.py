"""Rollouts and the MPPI planner shard over devices: two forced host devices give the one-device
answer, the collection both ways (XLA's partitioner, a thread and program per device). (Training
over two devices against one: ``test_distributed.py``.)

One subprocess per device count does both (importing JAX and MJX twice is most of the cost)."""

import os
import subprocess
import sys

import numpy as np

from stride_jax import _env

SCRIPT = """
import stride_jax, jax, numpy as np, sys
from stride_jax.sim import model, rollout_mjx
out, n = sys.argv[1], int(sys.argv[2])
assert len(jax.local_devices()) == n and len(rollout_mjx.mjx_devices()) == n
for split in rollout_mjx.SPLITS:  # 7 episodes in calls of 4 worlds: padded, uneven shares
    ticks = []
    ep = rollout_mjx.collect(model.load('pendulum'), jax.random.key(0), 7, 20, 4, split=split,
                             progress=ticks.append)
    assert sum(ticks) == 7, (split, ticks)
    np.save(out + f"/q_{split}.npy", ep.records.q)
    done = rollout_mjx.device_call(model.load('pendulum'), 20, 4, split=split)()  # benchmarks' call
    assert len(jax.tree.leaves(done)) > 0
# MPPI with a stochastic double integrator, its samples split over the devices.
import jax.numpy as jnp
from stride_jax.control import mppi
def dynamics(q, qd, u, k):
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
# the one helper behind both: a named leading axis over the devices, split evenly or refused
from stride_jax import distributed
sh = distributed.split_leading("worlds", None, 4)
assert (sh is None) == (n == 1) and (n == 1 or sh.spec == jax.sharding.PartitionSpec("worlds"))
if n > 1:
    try:
        rollout_mjx.world_sharding(3)
        raise SystemExit("3 worlds over 2 devices were not refused")
    except ValueError as e:
        assert "3 worlds do not split evenly over 2 devices" in str(e), e
"""


# In the default suite (~17 s on 2 cores): `stride data`'s default on several devices (a thread and
# program per device) is tested nowhere else.
def test_rollouts_and_planning_on_two_devices_match_one(tmp_path):
    outs, procs = [], []
    for n in (1, 2):  # side by side: each is mostly single-threaded compilation
        env = dict(os.environ)
        env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "--xla_cpu_enable_concurrency_optimized_scheduler=false")
                            + f" --xla_force_host_platform_device_count={n}")  # conftest's flags too
        env["NPROC"] = str(_env.pool_needed(n))  # MJX on both (rollout_mjx.mjx_devices)
        out = tmp_path / f"dev{n}"
        out.mkdir()
        procs.append(subprocess.Popen([sys.executable, "-c", SCRIPT, str(out), str(n)],
                                      env=env))
        outs.append(out)
    codes = [proc.wait(timeout=600) for proc in procs]
    assert codes == [0, 0], f"subprocess exit codes {codes}"
    one = np.load(outs[0] / "q_shard.npy")
    assert one.shape == (7, 20, 1) and np.abs(np.diff(one, axis=1)).max() > 1e-3  # it moved
    np.testing.assert_allclose(np.load(outs[0] / "q_threads.npy"), one, atol=1e-6)
    for split in ("shard", "threads"):
        np.testing.assert_allclose(np.load(outs[1] / f"q_{split}.npy"), one, atol=1e-6,
                                   err_msg=split)
    plans = [np.load(o / "plan.npy") for o in outs]
    assert np.abs(plans[0]).max() > 0.1  # the planner moved
    np.testing.assert_allclose(plans[1], plans[0], atol=1e-4)  # float rounding, 3 steps
