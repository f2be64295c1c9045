"""Wall-clock measurements shared by the benchmarks, the closed loop and the NFE figure: the
times (and median) of calls after a warm-up call, and the device's measured matmul peak."""

from __future__ import annotations

import statistics
import time
from typing import Callable


def wall_times(fn: Callable[[], object], repeats: int, warm_up: bool = True) -> list[float]:
    """Wall times (s) of ``repeats`` calls of ``fn`` after one warm-up call (which compiles;
    ``warm_up=False``: the caller made it). ``fn`` must block until its result is ready
    (``jax.block_until_ready``)."""
    if repeats < 1:
        raise ValueError(f"repeats must be >= 1, got {repeats}")
    if warm_up:
        fn()  # compile and warm up
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return times


def median_time(fn: Callable[[], object], repeats: int) -> float:
    """Median wall time (s) of ``repeats`` calls of ``fn`` after a warm-up (:func:`wall_times`)."""
    return statistics.median(wall_times(fn, repeats))


def peak_flops(n: int = 2048, repeats: int = 5, dtype: str = "float32") -> float:
    """Measured matmul throughput of the default device (FLOP/s): the best of ``repeats``
    ``[n, n] @ [n, n]`` products with operands of ``dtype`` (``float32`` or ``bfloat16``,
    accumulated in float32)."""
    import jax
    import jax.numpy as jnp

    a = jax.random.normal(jax.random.key(0), (n, n), jnp.float32).astype(dtype)
    f = jax.jit(lambda x: jnp.dot(x, x, preferred_element_type=jnp.float32))
    f(a).block_until_ready()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        f(a).block_until_ready()
        times.append(time.perf_counter() - t0)
    return 2 * n ** 3 / min(times)
