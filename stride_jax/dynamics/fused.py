"""Fused network passes for planners on GPUs: one Pallas (Triton) kernel per pass of an MLP.

A planner's model step on a GPU is bound by the number of kernels it launches, not by arithmetic
(``results/README.md``: ~70 kernels of ~3.5 us per horizon step, 13x above the FLOP floor). XLA
runs each of an MLP's matrix products as its own kernel, and a tangent or a transposed pass as
more of them. Here every pass is one kernel over blocks of rows (samples):

* :func:`jvp` -- outputs and their derivative along one tangent (the Lagrangian networks'
  forward and tangent passes together);
* :func:`vjp` -- the input cotangent of an output cotangent (the forward pass recomputed in the
  kernel, then the transposed pass);
* :func:`flow_euler` -- a whole flow-matching sample: ``nfe`` Euler steps of the vector field.

Each is written for one example, like the rest of the library: called unbatched it is plain JAX;
under ``vmap`` (a planner's samples) it becomes one kernel for the whole batch
(``jax.custom_batching.custom_vmap``) on a GPU, and the same batched maths in plain JAX on a CPU.
They are inference-only: nothing here is differentiable (training keeps XLA's autodiff).

Layout. A feature dimension is padded to a power of two (Triton's tensor shapes; padding
columns and rows are zero and stay zero). A program holds its rows' activations whole and walks
each layer's weights one tile of columns at a time in a loop (``fori_loop``, software-pipelined
by Triton), writing the layer's output through a per-program buffer. The networks are
:mod:`stride_jax.dynamics.mlp`'s (SiLU hidden layers, a linear output).

Status (one H100, Go1, 1024 samples; commands and numbers in ``results/README.md``): at the
paper's 256 x 3 a program streams ~0.7 MB of weights for only 16 rows, and the kernels are no
faster than XLA per pass (jvp 74 vs 47 us, vjp 64 vs 51 us, a flow sample 59 vs 60 us, 45 us
with bfloat16 products). At planning sizes they are: 64 x 3 per pass 19-24 us against XLA's
25-34, and a whole MPPI step (K = 1024, H = 30, STRIDE NFE 2) 6.09 ms in XLA, 5.41 ms fused,
5.12 ms fused with bfloat16 products. Select them with ``StructuredConfig.kernel``
(``bench-mppi --kernel``). A first version with the layers unrolled was 7x slower: ``ncu``
showed 32 registers and a 13.5 kB stack per thread, warps stalled on local memory (its weight
loads spilled), hence the tile loops.
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import functools
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

CHUNK = 64  # columns of a weight tile
ROWS = 16  # samples per kernel program (Triton's smallest matrix-product tile)
WARPS = 4  # warps per kernel program
STAGES = 2  # software-pipelining depth of the weight-tile loops

_INTERPRET = contextvars.ContextVar("stride_fused_interpret", default=False)


@contextlib.contextmanager
def interpret():
    """Inside this context (at trace time) the kernels run in Pallas' interpreter on any
    platform, CPU included: how the tests check the kernels against plain JAX."""
    token = _INTERPRET.set(True)
    try:
        yield
    finally:
        _INTERPRET.reset(token)


# --- the networks' parameters -----------------------------------------------------------------


def _layers(params: dict) -> list[tuple[jax.Array, jax.Array]]:
    """``[(W [din, dout], b [dout]), ...]`` of an :func:`mlp.mlp` network, input to output."""
    dense = params["params"]
    return [(dense[f"Dense_{i}"]["kernel"], dense[f"Dense_{i}"]["bias"])
            for i in range(len(dense))]


def _silu(z):
    return z * jax.nn.sigmoid(z)


def _silu_grad(z):
    s = jax.nn.sigmoid(z)
    return s * (1.0 + z * (1.0 - s))


# --- reference maths (one example or a batch: rows are the last-but-one axis) -----------------


def _forward_ref(layers, x):
    for i, (w, b) in enumerate(layers):
        x = x @ w + b
        if i < len(layers) - 1:
            x = _silu(x)
    return x


def _jvp_ref(layers, x, t):
    return jax.jvp(lambda x: _forward_ref(layers, x), (x,), (t,))


def _vjp_ref(layers, x, g):
    return jax.vjp(lambda x: _forward_ref(layers, x), x)[1](g)[0]


def _time_embedding(t: float, n: int) -> np.ndarray:
    """:func:`flow._time_embedding` at a static time (the Euler steps' times are static)."""
    freqs = np.pi * 2.0 ** np.arange(n // 2)
    return np.concatenate([np.sin(freqs * t), np.cos(freqs * t)]).astype(np.float32)


def _flow_ref(layers, z, c, nfe, time_features):
    """``nfe`` Euler steps of ``v(z, t | c)`` (:func:`flow.integrate`'s Euler path)."""
    dt = 1.0 / nfe
    for i in range(nfe):
        emb = jnp.broadcast_to(_time_embedding(i * dt, time_features),
                               z.shape[:-1] + (time_features,))
        z = z + dt * _forward_ref(layers, jnp.concatenate([z, emb, c], axis=-1))
    return z


# --- the kernels ------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class _Dim:
    """A feature dimension of ``size`` padded to a power of two (Triton's tensor shapes) and
    worked on in tiles of ``tile`` columns."""

    size: int
    padded: int
    tile: int

    @classmethod
    def of(cls, size: int) -> "_Dim":
        padded = max(16, 1 << (size - 1).bit_length())
        return cls(size, padded, min(CHUNK, padded))

    @property
    def n(self) -> int:
        return self.padded // self.tile


def _pad_cols(x: jax.Array, dim: _Dim) -> jax.Array:
    return jnp.pad(x, [(0, 0)] * (x.ndim - 1) + [(0, dim.padded - x.shape[-1])])


def _pad_weight(w: jax.Array, din: _Dim, dout: _Dim) -> jax.Array:
    return jnp.pad(w, [(0, din.padded - w.shape[0]), (0, dout.padded - w.shape[1])])


def _dot(a, b):
    """``a @ b`` in the weights' type ``b.dtype``, accumulated in float32."""
    return jnp.dot(a.astype(b.dtype), b, preferred_element_type=jnp.float32)


def _dot_t(a, b):
    """``a @ b.T``."""
    return jax.lax.dot_general(a.astype(b.dtype), b, (((1,), (1,)), ((), ())),
                               preferred_element_type=jnp.float32)


def _load_in(ref, size: int):
    """A row input's block, its columns past ``size`` (beyond the array) read as zeros: the
    inputs need no padded copy (one kernel launch less each)."""
    from jax.experimental.pallas import triton as pl_triton

    cols = jax.lax.broadcasted_iota(jnp.int32, ref.shape, 1)
    return pl_triton.load(ref, mask=cols < size, other=0.0)


def _put(ref, cols, value, size: int | None = None) -> None:
    """``ref[:, cols] = value``; with ``size``, only the columns below it (an output array
    narrower than its block)."""
    if size is None:
        ref[:, cols] = value
        return
    from jax.experimental.pallas import triton as pl_triton

    index = cols.start + jax.lax.broadcasted_iota(jnp.int32, value.shape, 1)
    pl_triton.store(ref.at[:, cols], value, mask=index < size)


def _barrier() -> None:
    """Every thread of the program gets here (and sees the others' stores) before any goes on."""
    if not _INTERPRET.get():
        from jax.experimental.pallas import triton as pl_triton
        pl_triton.debug_barrier()


def _tiles(dim: _Dim, body: Callable) -> None:
    """``body(cols)`` for each tile of ``dim``'s columns, as a loop: a weight tile is loaded
    inside it, where Triton pipelines the loads (the unrolled first version spilled them)."""
    from jax.experimental import pallas as pl

    def step(j, carry):
        body(pl.ds(pl.multiple_of(j * dim.tile, dim.tile), dim.tile))
        return carry

    jax.lax.fori_loop(0, dim.n, step, 0)
    _barrier()


def _dense(h, w_ref, b_ref, dout: _Dim, out_ref, act: bool, t=None, t_ref=None, z_ref=None,
           out_size: int | None = None):
    """``out = act(h @ W + b)`` into ``out_ref`` tile by tile; with a tangent ``t``, its image
    ``act'(z) (t @ W)`` into ``t_ref``; ``z_ref`` keeps the pre-activations; ``out_size``: the
    width of output arrays narrower than the block."""
    def body(cols):
        w = w_ref[:, cols]
        z = _dot(h, w) + b_ref[:, cols]
        if z_ref is not None:
            z_ref[:, cols] = z
        if t is not None:
            zt = _dot(t, w)
            _put(t_ref, cols, _silu_grad(z) * zt if act else zt, out_size)
        _put(out_ref, cols, _silu(z) if act else z, out_size)

    _tiles(dout, body)


def _kernel(mode: str, dims: tuple[_Dim, ...], nfe: int = 0) -> Callable:
    """The kernel body of one mode; ``dims`` are the layers' feature dimensions, input first
    (for ``flow``: the latent's, the context's, then the layers' outputs). Activations go
    through per-program buffers (extra outputs, alternating between two so that no layer writes
    where the one before still reads), whole rows in, one weight tile at a time."""
    n_layers = len(dims) - 1

    if mode == "jvp":
        def kernel(x_ref, t_ref, *refs):
            w, (y_ref, yt_ref, a0, a1, t0, t1) = refs[:2 * n_layers], refs[2 * n_layers:]
            h, t = _load_in(x_ref, dims[0].size), _load_in(t_ref, dims[0].size)
            for k in range(n_layers):
                last = k == n_layers - 1
                out, t_out = (y_ref, yt_ref) if last else ((a0, t0), (a1, t1))[k % 2]
                _dense(h, w[2 * k], w[2 * k + 1], dims[k + 1], out, not last, t, t_out,
                       out_size=dims[-1].size if last else None)
                if not last:
                    width = dims[k + 1].padded
                    h, t = out[:, :width], t_out[:, :width]
    elif mode == "vjp":
        def kernel(x_ref, g_ref, *refs):
            w, gx_ref = refs[:2 * n_layers], refs[2 * n_layers]
            a, gb = refs[2 * n_layers + 1:2 * n_layers + 3], refs[2 * n_layers + 3:2 * n_layers + 5]
            zs = refs[2 * n_layers + 5:]
            h = _load_in(x_ref, dims[0].size)
            for k in range(n_layers - 1):  # hidden layers: keep the pre-activations
                _dense(h, w[2 * k], w[2 * k + 1], dims[k + 1], a[k % 2], True, z_ref=zs[k])
                h = a[k % 2][:, :dims[k + 1].padded]
            g = _load_in(g_ref, dims[-1].size)
            for k in reversed(range(n_layers)):
                out = gx_ref if k == 0 else gb[k % 2]

                def body(cols, k=k, g=g, out=out):
                    gi = _dot_t(g, w[2 * k][cols, :])
                    if k > 0:
                        gi = gi * _silu_grad(zs[k - 1][:, cols])
                    _put(out, cols, gi, None if k > 0 else dims[0].size)

                _tiles(dims[k], body)
                if k > 0:
                    g = out[:, :dims[k].padded]
    elif mode == "flow":
        # refs: z0, c | W_z, W_c, time rows (the time embedding's product plus the first bias,
        # one row per Euler step), then the later layers' (W, b) | out, buffers
        hidden = dims[2:]

        def kernel(z_ref, c_ref, wz_ref, wc_ref, tb_ref, *refs):
            n_w = 2 * (len(hidden) - 1)
            w, (out_ref, cw, a0, a1) = refs[:n_w], refs[n_w:]
            c = _load_in(c_ref, dims[1].size)

            def context(cols):
                cw[:, cols] = _dot(c, wc_ref[:, cols])

            _tiles(hidden[0], context)
            z = _load_in(z_ref, dims[0].size)
            for i in range(nfe):
                def first(cols, i=i, z=z):
                    a0[:, cols] = _silu(_dot(z, wz_ref[:, cols]) + cw[:, cols]
                                        + tb_ref[i:i + 1, cols])

                _tiles(hidden[0], first)
                h = a0[:, :hidden[0].padded]
                for k in range(len(hidden) - 1):
                    last = k == len(hidden) - 2
                    out = (a1, a0)[k % 2]
                    _dense(h, w[2 * k], w[2 * k + 1], hidden[k + 1], out, not last)
                    h = out[:, :hidden[k + 1].padded]
                z = z + h / nfe
            _put(out_ref, slice(0, dims[0].padded), z, dims[0].size)
    else:
        raise ValueError(f"unknown kernel mode {mode!r}")
    return kernel


def _pallas(kernel: Callable, rows: list[tuple[jax.Array, int]], consts: list[jax.Array],
            outs: list[tuple[int, int]], buffers: list[int]) -> list[jax.Array]:
    """Runs ``kernel`` over blocks of ``ROWS`` rows of the ``rows`` inputs (``(array [B, n],
    block width)``: the kernel masks the block's columns past ``n``), with ``consts``
    (weights) whole; returns the outputs ``[B, n]`` for ``(n, block width)`` in ``outs``
    (``buffers``: the widths of the per-program buffers, outputs that are dropped)."""
    from jax.experimental import pallas as pl
    from jax.experimental.pallas import triton as pl_triton

    batch = rows[0][0].shape[0]
    padded = -(-batch // ROWS) * ROWS
    arrays = [r if padded == batch else jnp.pad(r, ((0, padded - batch), (0, 0)))
              for r, _ in rows]
    consts = [c.reshape(1, -1) if c.ndim == 1 else c for c in consts]
    row_spec = lambda cols: pl.BlockSpec((ROWS, cols), lambda i: (i, 0))
    shapes = list(outs) + [(w, w) for w in buffers]
    results = pl.pallas_call(
        kernel,
        out_shape=[jax.ShapeDtypeStruct((padded, n), jnp.float32) for n, _ in shapes],
        grid=(padded // ROWS,),
        in_specs=[row_spec(block) for _, block in rows]
        + [pl.BlockSpec(c.shape, lambda i: (0, 0)) for c in consts],
        out_specs=[row_spec(block) for _, block in shapes],
        interpret=_INTERPRET.get(),
        compiler_params=pl_triton.CompilerParams(num_warps=WARPS, num_stages=STAGES),
        name="stride_fused_mlp",
    )(*arrays, *consts)
    return [r if padded == batch else r[:batch] for r in results[:len(outs)]]


def _padded_layers(layers, dims, dtype):
    out = []
    for (w, b), din, dout in zip(layers, dims[:-1], dims[1:]):
        out += [_pad_weight(w, din, dout).astype(dtype), _pad_cols(b, dout)]
    return out


def _dims(layers) -> tuple[_Dim, ...]:
    return tuple(_Dim.of(n) for n in [layers[0][0].shape[0]] + [w.shape[1] for w, _ in layers])


def _jvp_kernel(layers, x, t, dtype):
    dims = _dims(layers)
    width = max(d.padded for d in dims)
    return tuple(_pallas(_kernel("jvp", dims), [(x, dims[0].padded), (t, dims[0].padded)],
                         _padded_layers(layers, dims, dtype),
                         [(dims[-1].size, dims[-1].padded)] * 2, [width] * 4))


def _vjp_kernel(layers, x, g, dtype):
    dims = _dims(layers)
    width = max(d.padded for d in dims)
    (gx,) = _pallas(_kernel("vjp", dims), [(x, dims[0].padded), (g, dims[-1].padded)],
                    _padded_layers(layers, dims, dtype), [(dims[0].size, dims[0].padded)],
                    [width] * 4 + [d.padded for d in dims[1:-1]])
    return gx


def _flow_kernel(layers, z, c, nfe, time_features, dtype):
    (w1, b1), rest = layers[0], layers[1:]
    nz = z.shape[-1]
    dz, dc = _Dim.of(nz), _Dim.of(c.shape[-1])
    hidden = tuple(_Dim.of(w.shape[1]) for w, _ in layers)
    # the first layer split by its input blocks: latent, time embedding, context; the time's
    # product is static per step and joins the bias
    w_z, w_t, w_c = w1[:nz], w1[nz:nz + time_features], w1[nz + time_features:]
    times = np.stack([_time_embedding(i / nfe, time_features) for i in range(nfe)])
    rows = 1 << (nfe - 1).bit_length()  # a power of two for Triton
    time_rows = jnp.pad(times @ w_t + b1, ((0, rows - nfe), (0, hidden[0].padded - b1.shape[0])))
    consts = [_pad_weight(w_z, dz, hidden[0]).astype(dtype),
              _pad_weight(w_c, dc, hidden[0]).astype(dtype), time_rows]
    consts += _padded_layers(rest, hidden, dtype)
    width = max(d.padded for d in hidden)
    (out,) = _pallas(_kernel("flow", (dz, dc) + hidden, nfe), [(z, dz.padded), (c, dc.padded)],
                     consts, [(nz, dz.padded)], [width] * 3)
    return out


# --- one example in, a batch under vmap -------------------------------------------------------


def _batched(kernel_fn: Callable, ref_fn: Callable, n_out: int) -> Callable:
    """``f(layers, *xs)`` for one example; under ``vmap`` (unbatched weights) one kernel for the
    batch on GPUs (``kernel_fn``), the batched reference on CPUs (``ref_fn``)."""
    @jax.custom_batching.custom_vmap
    def f(layers, *xs):
        return ref_fn(layers, *xs)

    @f.def_vmap
    def rule(axis_size, in_batched, layers, *xs):
        layers_batched, xs_batched = in_batched[0], in_batched[1:]
        out_batched = (True,) * n_out if n_out > 1 else True
        if any(jax.tree.leaves(layers_batched)):  # per-sample weights: no shared kernel
            axes = (jax.tree.map(lambda b: 0 if b else None, layers_batched),
                    *[0 if b else None for b in xs_batched])
            return jax.vmap(ref_fn, in_axes=axes)(layers, *xs), out_batched
        xs = [x if b else jnp.broadcast_to(x, (axis_size,) + x.shape)
              for x, b in zip(xs, xs_batched)]
        if _INTERPRET.get():
            return kernel_fn(layers, *xs), out_batched
        return jax.lax.platform_dependent(layers, *xs, cpu=ref_fn, default=kernel_fn), \
            out_batched

    return f


def jvp(params: dict, x: jax.Array, t: jax.Array, dtype=jnp.float32
        ) -> tuple[jax.Array, jax.Array]:
    """``(f(x), df(x) t)`` of an :func:`mlp.mlp` network with ``params``; ``x, t [din]``.
    ``dtype``: the kernel's matrix-product inputs (float32 or bfloat16; accumulation float32)."""
    f = _batched(functools.partial(_jvp_kernel, dtype=dtype), _jvp_ref, 2)
    return f(_layers(params), x, t)


def vjp(params: dict, x: jax.Array, g: jax.Array, dtype=jnp.float32) -> jax.Array:
    """``df(x)^T g`` ``[din]`` of an :func:`mlp.mlp` network, ``g [dout]``."""
    f = _batched(functools.partial(_vjp_kernel, dtype=dtype), _vjp_ref, 1)
    return f(_layers(params), x, g)


def flow_euler(params: dict, z0: jax.Array, context: jax.Array, nfe: int,
               time_features: int, dtype=jnp.float32) -> jax.Array:
    """A flow-matching sample ``[dim]`` from ``z0 [dim]``: :func:`flow.integrate` with Euler
    steps, the vector field's ``params`` and its input ``(z, time embedding, context)``."""
    if nfe < 1:
        raise ValueError(f"flow_euler needs nfe >= 1, got {nfe}")
    f = _batched(lambda layers, z, c: _flow_kernel(layers, z, c, nfe, time_features, dtype),
                 lambda layers, z, c: _flow_ref(layers, z, c, nfe, time_features), 1)
    return f(_layers(params), z0, context)


KERNELS = {"xla": None, "pallas": jnp.float32, "pallas-bf16": jnp.bfloat16}


def kernel_dtype(kernel: str):
    """The fused kernels' product type for a kernel choice (None: XLA's own ops)."""
    if kernel not in KERNELS:
        raise ValueError(f"unknown kernel {kernel!r}; available: {', '.join(KERNELS)}")
    return KERNELS[kernel]


__all__ = ["KERNELS", "flow_euler", "interpret", "jvp", "kernel_dtype", "vjp"]
