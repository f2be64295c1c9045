"""One fused jvp kernel (``stride_jax.dynamics.fused``) timed as a single jitted call, for one
kernel layout: how its time depends on the batch, the network and the layout (GPU study).

    python experiments/probes/fused_jvp_time.py HIDDEN DEPTH SAMPLES CHUNK,ROWS,WARPS DTYPE
    python experiments/probes/fused_jvp_time.py 256 3 1024 64,16,4 bfloat16

Prints the median of 20 calls (dispatch included) with the weights as constants of the compiled
call ("const") and as arguments ("arg"). ``SAMPLES`` = 16 is one kernel program.
"""

import sys

import jax
import jax.numpy as jnp

import stride_jax
from stride_jax.dynamics import fused, fused_pallas, mlp
from stride_jax.timing import median_time

stride_jax.set_xla_flags()  # before JAX starts: small CPUs deadlock without
hidden, depth, K = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
fused_pallas.CHUNK, fused_pallas.ROWS, fused_pallas.WARPS = (int(v) for v in sys.argv[4].split(","))
dtype = jnp.dtype(sys.argv[5])
init, apply = mlp.mlp(mlp.MLPConfig(hidden, depth), 166)  # Go1's one-network prior: 21 -> 166
params = init(jax.random.key(0), 21)
x = jax.random.normal(jax.random.key(1), (K, 21))
t = x * 0.5
const = jax.jit(jax.vmap(lambda x, t: fused.jvp(params, x, t, dtype)))
arg = jax.jit(lambda p, x, t: jax.vmap(lambda x, t: fused.jvp(p, x, t, dtype))(x, t))
for name, fn, args in [("const", const, (x, t)), ("arg", arg, (params, x, t))]:
    median = median_time(lambda: jax.block_until_ready(fn(*args)), 20)
    print(sys.argv[4:], hidden, depth, K, name, f"{1e6 * median:.1f} us", flush=True)
