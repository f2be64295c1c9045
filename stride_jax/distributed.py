"""Several processes, one job: data generation and training across hosts (``jax.distributed``).

One command per node, the same on each but for its process id::

    stride train --robot go1 --distributed.coordinator node0:12355 \\
        --distributed.num-processes 2 --distributed.process-id 0     # on node0
    ... --distributed.process-id 1                                   # on node1

or with the settings in the environment (``STRIDE_COORDINATOR``, ``STRIDE_NUM_PROCESSES``,
``STRIDE_PROCESS_ID``), or ``--distributed.coordinator auto`` where JAX detects the cluster itself
(SLURM, Open MPI, Kubernetes, Cloud TPU: ``jax.distributed.initialize()`` with no arguments).
Without any of these a job runs as one process, as before.

What each job does with several processes:

* ``stride data``: each process simulates its contiguous share of the episodes (every episode's
  draws come from its own key, so the shares are the episodes one process would make); the
  shares are gathered and process 0 writes the dataset, byte for byte the one process's.
* ``stride train``: data parallel over every device of every process (one mesh): each step's
  minibatch is split over the devices, the gradients all-reduced by XLA; parameters and
  optimiser state are replicated, so every process holds the same model; process 0 writes the
  logs, every process takes part in the (orbax) checkpoints.

Every process must see the same dataset folder and run folder (a shared file system).
"""

from __future__ import annotations

import dataclasses
import os
from typing import Any

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec


@dataclasses.dataclass(frozen=True)
class DistributedConfig:
    """How this process joins a multi-process job (all empty: a single process).

    Attributes:
      coordinator: ``host:port`` of process 0 (``auto``: JAX detects the cluster); empty:
        ``$STRIDE_COORDINATOR``, else a single process.
      num_processes: processes in the job (0: ``$STRIDE_NUM_PROCESSES``).
      process_id: this process's index, 0 .. num_processes - 1 (-1: ``$STRIDE_PROCESS_ID``).
    """

    coordinator: str = ""
    num_processes: int = 0
    process_id: int = -1


def resolve(cfg: DistributedConfig, env: dict | None = None) -> DistributedConfig | None:
    """``cfg`` with the environment filled in, or None for a single process; a clear error for
    a partial or inconsistent setting."""
    env = os.environ if env is None else env
    coordinator = cfg.coordinator or env.get("STRIDE_COORDINATOR", "")
    if not coordinator:
        return None
    if coordinator == "auto":
        return DistributedConfig("auto")
    n = cfg.num_processes or int(env.get("STRIDE_NUM_PROCESSES", "0") or 0)
    pid = cfg.process_id if cfg.process_id >= 0 else int(env.get("STRIDE_PROCESS_ID", "-1"))
    if n < 1 or not 0 <= pid < n:
        raise ValueError(f"distributed: coordinator {coordinator!r} needs num_processes >= 1 and "
                         f"0 <= process_id < num_processes, got {n} and {pid} (flags "
                         "--distributed.num-processes/--distributed.process-id or "
                         "STRIDE_NUM_PROCESSES/STRIDE_PROCESS_ID)")
    return DistributedConfig(coordinator, n, pid)


def initialize(cfg: DistributedConfig = DistributedConfig()) -> bool:
    """Joins the job ``cfg`` describes (before any JAX computation); False for a single
    process. Idempotent."""
    cfg = resolve(cfg)
    if cfg is None:
        return False
    if jax.distributed.is_initialized():
        return True
    if cfg.coordinator == "auto":
        jax.distributed.initialize()
    else:
        jax.distributed.initialize(cfg.coordinator, cfg.num_processes, cfg.process_id)
    return True


def is_main() -> bool:
    """Whether this is the process that writes files (process 0)."""
    return jax.process_index() == 0


def share(n: int) -> slice:
    """This process's contiguous share of ``n`` items (``n`` must split evenly)."""
    p, k = jax.process_count(), jax.process_index()
    if n % p:
        raise ValueError(f"{n} items do not split evenly over {p} processes; use a multiple "
                         f"of {p}")
    return slice(k * n // p, (k + 1) * n // p)


def gather(tree: Any) -> Any:
    """Every process's arrays (numpy, leading axis its share), concatenated in process order
    on every process; the tree itself on a single process."""
    if jax.process_count() == 1:
        return tree
    from jax.experimental import multihost_utils
    return jax.tree.map(np.asarray, multihost_utils.process_allgather(tree, tiled=True))


def barrier(name: str) -> None:
    """Waits until every process got here (no-op on a single process)."""
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils
        multihost_utils.sync_global_devices(name)


def split_leading(axis: str, devices: list | None = None, n: int | None = None
                  ) -> NamedSharding | None:
    """A leading array axis named ``axis`` split over ``devices`` (all local devices; None on a
    single one: nothing to split); ``n``, the axis's length where given, must split evenly."""
    devices = jax.local_devices() if devices is None else devices
    if len(devices) == 1:
        return None
    if n is not None and n % len(devices):
        raise ValueError(f"{n} {axis} do not split evenly over {len(devices)} devices; use a "
                         f"multiple of {len(devices)}")
    return NamedSharding(Mesh(np.array(devices), (axis,)), PartitionSpec(axis))


def mesh(axis: str = "batch") -> Mesh:
    """All devices of all processes on one axis."""
    return Mesh(np.array(jax.devices()), (axis,))


def replicate(tree: Any, on: Mesh) -> Any:
    """Host or local arrays as global arrays replicated on every device of ``on`` (each process
    passes the same values)."""
    rep = NamedSharding(on, PartitionSpec())

    def one(x):
        x = np.asarray(x)
        return jax.make_array_from_callback(x.shape, rep, lambda idx: x[idx])
    return jax.tree.map(one, tree)


def to_host(tree: Any) -> Any:
    """Replicated global arrays as numpy (every process holds a full copy)."""
    return jax.tree.map(lambda a: np.asarray(a.addressable_data(0))
                        if isinstance(a, jax.Array) else np.asarray(a), tree)
