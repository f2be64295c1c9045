"""The Pallas (Triton) kernels behind :mod:`stride_jax.dynamics.fused`: one MLP pass per
kernel over blocks of ``ROWS`` samples.

Layout. A feature dimension is padded to a power of two (Triton's tensor shapes; padding
columns and rows are zero and stay zero; row inputs narrower than their block are read with
masks). A program holds its rows' activations whole and walks each layer's weights one tile of
``CHUNK`` columns at a time in a loop (``fori_loop``, software-pipelined by Triton, ``STAGES``
deep), writing the layer's output through a per-program buffer. The layout constants are module
attributes so that ``experiments/probes/fused_kernels.py`` can time other layouts.
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
from typing import Callable

import jax
import jax.numpy as jnp

from stride_jax.dynamics.time_embedding import time_embedding

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


def _silu(z):
    return z * jax.nn.sigmoid(z)


def _silu_grad(z):
    s = jax.nn.sigmoid(z)
    return s * (1.0 + z * (1.0 - s))


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


OUT_CHUNK = 256  # transposed passes: columns of a layer's outputs per piece of a weight tile


def _forward(dims, w, h, bufs, outs, t=None, zs=None, out_size=None) -> None:
    """The layers of ``w`` forward from ``h`` (and along the tangent ``t``): hidden layers
    through ``bufs = (a0, a1[, t0, t1])``, the last into ``outs = (y_ref[, yt_ref])``; ``zs``
    keeps the hidden pre-activations; ``out_size``: the width of a narrower output array."""
    n_l = len(dims) - 1
    for k in range(n_l):
        last = k == n_l - 1
        out = outs[0] if last else bufs[k % 2]
        t_out = None if t is None else (outs[1] if last else bufs[2 + k % 2])
        _dense(h, w[2 * k], w[2 * k + 1], dims[k + 1], out, not last, t, t_out,
               z_ref=None if last or zs is None else zs[k], out_size=out_size if last else None)
        if not last:
            width = dims[k + 1].padded
            h = out[:, :width]
            t = None if t is None else t_out[:, :width]


def _transposed(dims, w, zs, g, out_ref, bufs, g_ref=None, in_size=None) -> None:
    """The transposed pass of the output cotangent ``g`` into ``out_ref`` (``zs``: the hidden
    pre-activations; ``in_size``: the width of a narrower input-cotangent array). The last
    layer's weight tiles span all its outputs; wider than ``OUT_CHUNK`` (G1's 627 outputs: 256
    kB in float32, past an SM's shared memory) they are read in pieces, ``g`` through
    ``g_ref``."""
    last = len(dims) - 2
    pieces = max(1, dims[-1].padded // OUT_CHUNK)
    if pieces > 1:
        g_ref[...] = g
        _barrier()
    piece = lambda p: slice(p * OUT_CHUNK, (p + 1) * OUT_CHUNK)
    for k in reversed(range(len(dims) - 1)):
        out = out_ref if k == 0 else bufs[k % 2]

        def body(cols, k=k, g=g, out=out):
            if k != last or pieces == 1:
                gi = _dot_t(g, w[2 * k][cols, :])
            else:
                gi = sum(_dot_t(g_ref[:, piece(p)], w[2 * k][cols, piece(p)])
                         for p in range(pieces))
            if k > 0:
                gi = gi * _silu_grad(zs[k - 1][:, cols])
            _put(out, cols, gi, None if k > 0 else in_size)

        _tiles(dims[k], body)
        if k > 0:
            g = out[:, :dims[k].padded]


def _flow_steps(dims, nfe, c, wz_ref, wc_ref, tb_ref, w, cw, a0, a1, z):
    """``nfe`` Euler steps of the flow from ``z`` given its context ``c``; ``dims``: the
    latent's, the context's, then the layers' outputs. The first layer is split by its inputs
    (``W_z``, ``W_c``, and ``tb_ref``: the time embedding's product plus the bias, one row per
    step); ``cw`` keeps the context's product."""
    hidden = dims[2:]

    def context(cols):
        cw[:, cols] = _dot(c, wc_ref[:, cols])

    _tiles(hidden[0], context)
    for i in range(nfe):
        def first(cols, i=i, z=z):
            a0[:, cols] = _silu(_dot(z, wz_ref[:, cols]) + cw[:, cols] + tb_ref[i:i + 1, cols])

        _tiles(hidden[0], first)
        h = a0[:, :hidden[0].padded]
        for k in range(len(hidden) - 1):
            last = k == len(hidden) - 2
            out = (a1, a0)[k % 2]
            _dense(h, w[2 * k], w[2 * k + 1], hidden[k + 1], out, not last)
            h = out[:, :hidden[k + 1].padded]
        z = z + h / nfe
    return z


def _kernel(mode: str, dims: tuple[_Dim, ...], nfe: int = 0) -> Callable:
    """The kernel body of one mode; ``dims`` are the layers' feature dimensions, input first
    (for ``flow``: the latent's, the context's, then the layers' outputs). Activations go
    through per-program buffers (extra outputs, alternating between two so that no layer writes
    where the one before still reads), whole rows in, one weight tile at a time."""
    n_layers = len(dims) - 1

    if mode == "jvp":
        def kernel(x_ref, t_ref, *refs):
            w, (y_ref, yt_ref, a0, a1, t0, t1) = refs[:2 * n_layers], refs[2 * n_layers:]
            _forward(dims, w, _load_in(x_ref, dims[0].size), (a0, a1, t0, t1), (y_ref, yt_ref),
                     _load_in(t_ref, dims[0].size), out_size=dims[-1].size)
    elif mode == "vjp":
        def kernel(x_ref, g_ref, *refs):
            w, gx_ref = refs[:2 * n_layers], refs[2 * n_layers]
            a, gb = refs[2 * n_layers + 1:2 * n_layers + 3], refs[2 * n_layers + 3:2 * n_layers + 5]
            zs = refs[2 * n_layers + 5:]
            h = _load_in(x_ref, dims[0].size)
            for k in range(n_layers - 1):  # hidden layers: keep the pre-activations
                _dense(h, w[2 * k], w[2 * k + 1], dims[k + 1], a[k % 2], True, z_ref=zs[k])
                h = a[k % 2][:, :dims[k + 1].padded]
            _transposed(dims, w, zs, _load_in(g_ref, dims[-1].size), gx_ref, gb, a[0],
                        in_size=dims[0].size)
    elif mode == "flow":
        hidden = dims[2:]

        def kernel(z_ref, c_ref, wz_ref, wc_ref, tb_ref, *refs):
            n_w = 2 * (len(hidden) - 1)
            w, (out_ref, cw, a0, a1) = refs[:n_w], refs[n_w:]
            z = _flow_steps(dims, nfe, _load_in(c_ref, dims[1].size), wz_ref, wc_ref, tb_ref, w,
                            cw, a0, a1, _load_in(z_ref, dims[0].size))
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


# Triton stages a program's weight tiles in shared memory (227 KiB a block on an H100). Measured
# there (experiments/probes/fused_step_smem.py, results/gpu_tests/): kernels compile while every layer's
# padded inputs x outputs stay within 2^16 -- Go1's networks up to 256 wide, G1's mass network
# (627 outputs, padded 1024) up to 64; G1 at 128 asks for 324 KiB. Larger layers run in XLA.
MAX_TILE = 1 << 16


def fits(weights) -> bool:
    """Whether the kernels over ``weights`` (a pytree of one or more networks' layers,
    ``W [din, dout]`` and biases) fit shared memory (:data:`MAX_TILE`)."""
    return all(_Dim.of(w.shape[0]).padded * _Dim.of(w.shape[1]).padded <= MAX_TILE
               for w in jax.tree.leaves(weights) if w.ndim == 2)


def _dims(layers) -> tuple[_Dim, ...]:
    return tuple(_Dim.of(n) for n in [layers[0][0].shape[0]] + [w.shape[1] for w, _ in layers])


def jvp_batched(layers, x, t, dtype):
    """``(y [B, dout], y_t [B, dout])`` of the network ``layers`` at ``x, t [B, din]``."""
    dims = _dims(layers)
    width = max(d.padded for d in dims)
    return tuple(_pallas(_kernel("jvp", dims), [(x, dims[0].padded), (t, dims[0].padded)],
                         _padded_layers(layers, dims, dtype),
                         [(dims[-1].size, dims[-1].padded)] * 2, [width] * 4))


def vjp_batched(layers, x, g, dtype):
    """``g_x [B, din]`` for the output cotangents ``g [B, dout]``."""
    dims = _dims(layers)
    width = max(d.padded for d in dims)
    (gx,) = _pallas(_kernel("vjp", dims), [(x, dims[0].padded), (g, dims[-1].padded)],
                    _padded_layers(layers, dims, dtype), [(dims[0].size, dims[0].padded)],
                    [width] * 4 + [d.padded for d in dims[1:-1]])
    return gx


def flow_batched(layers, z, c, nfe, time_features, dtype):
    """``nfe`` Euler steps of the vector field ``layers`` from ``z [B, dim]`` given ``c``."""
    (w1, b1), rest = layers[0], layers[1:]
    nz = z.shape[-1]
    dz, dc = _Dim.of(nz), _Dim.of(c.shape[-1])
    hidden = tuple(_Dim.of(w.shape[1]) for w, _ in layers)
    # the first layer split by its input blocks: latent, time embedding, context; the time's
    # product is static per step and joins the bias
    w_z, w_t, w_c = w1[:nz], w1[nz:nz + time_features], w1[nz + time_features:]

    times = jnp.stack([time_embedding(i / nfe, time_features) for i in range(nfe)])
    rows = 1 << (nfe - 1).bit_length()  # a power of two for Triton
    time_rows = jnp.pad(times @ w_t + b1, ((0, rows - nfe), (0, hidden[0].padded - b1.shape[0])))
    consts = [_pad_weight(w_z, dz, hidden[0]).astype(dtype),
              _pad_weight(w_c, dc, hidden[0]).astype(dtype), time_rows]
    consts += _padded_layers(rest, hidden, dtype)
    width = max(d.padded for d in hidden)
    (out,) = _pallas(_kernel("flow", (dz, dc) + hidden, nfe), [(z, dz.padded), (c, dc.padded)],
                     consts, [(nz, dz.padded)], [width] * 3)
    return out
