"""Wall time of a batch of small SPD solves, ``M x = b`` (the structured model step's solve), by
LAPACK's Cholesky (``cho_solve``, what the models used before), by Gauss-Jordan elimination
vmapped (batch first) and by :func:`stride_jax.dynamics.linalg.spd_solve` (Gauss-Jordan with the
batch last on a CPU); jitted, median of 300 calls, with the largest difference to Cholesky.

    python experiments/probes/spd_solve_time.py --batch 128 --n 18
"""

import argparse
import time

import stride_jax
import jax
import jax.numpy as jnp
import numpy as np

from stride_jax.dynamics import linalg


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--batch", type=int, default=128)
    p.add_argument("--n", type=int, default=18)
    a = p.parse_args()
    A = jax.random.normal(jax.random.key(0), (a.batch, a.n, a.n))
    M = A @ jnp.swapaxes(A, 1, 2) + a.n * jnp.eye(a.n)
    b = jax.random.normal(jax.random.key(1), (a.batch, a.n))
    solvers = {"cholesky (LAPACK)": linalg._solve_cholesky,
               "gauss-jordan, batch first": linalg._gauss_jordan,
               "spd_solve (batch last)": linalg.spd_solve}
    ref = jax.vmap(linalg._solve_cholesky)(M, b)
    for name, solve in solvers.items():
        f = jax.jit(jax.vmap(solve))
        jax.block_until_ready(f(M, b))
        times = []
        for _ in range(300):
            t0 = time.perf_counter()
            jax.block_until_ready(f(M, b))
            times.append(time.perf_counter() - t0)
        err = float(jnp.abs(f(M, b) - ref).max())
        print(f"{name:28s} {1e3 * np.median(times):.3f} ms for {a.batch} systems of {a.n} "
              f"(max |x - x_cholesky| {err:.1e})", flush=True)


if __name__ == "__main__":
    stride_jax.set_xla_flags()  # before JAX starts: small CPUs deadlock without
    main()
