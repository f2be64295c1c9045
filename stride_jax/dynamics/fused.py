"""Fused network passes for planners on GPUs: one Pallas (Triton) kernel per pass of an MLP.

A planner's model step on a GPU is bound by the number of kernels it launches, not by arithmetic
(``results/README.md``: ~70 kernels of ~3.5 us per horizon step, 13x above the FLOP floor). XLA
runs each of an MLP's matrix products as its own kernel, and a tangent or a transposed pass as
more of them. Here every pass is one kernel over a block of rows (samples), with the layers'
activations kept on chip:

* :func:`jvp` -- outputs and their derivative along one tangent (the Lagrangian networks'
  forward and tangent passes together);
* :func:`vjp` -- the input cotangent of an output cotangent (the forward pass recomputed in the
  kernel, then the transposed pass);
* :func:`flow_euler` -- a whole flow-matching sample: ``nfe`` Euler steps of the vector field.

Each is written for one example, like the rest of the library: called unbatched it is plain JAX;
under ``vmap`` (a planner's samples) it becomes one kernel for the whole batch
(``jax.custom_batching.custom_vmap``) on a GPU, and the same batched maths in plain JAX on a CPU.
They are inference-only: nothing here is differentiable (training keeps XLA's autodiff).

Layout. A feature dimension is cut into chunks of equal power-of-two width (Triton's blocks);
a layer is a grid of weight blocks, and its product is a sum of block products: no tensor in the
kernel is wider than a chunk, so hidden widths of any size fit in shared memory. Padding columns
and rows are zero and stay zero. The networks are :mod:`stride_jax.dynamics.mlp`'s (SiLU hidden
layers, a linear output).

Status (measured on one H100, Go1's one-network prior 256 x 3, 1024 samples; commands and numbers
in ``results/README.md``): correct, but **slower than XLA, so no model uses these kernels yet**.
A fused forward + tangent pass takes 0.56 ms where XLA's vmapped ``jax.jvp`` takes 0.06 ms
(30 passes in one call), 0.14 ms with bfloat16 products (``DTYPE``; one call, dispatch included,
against 0.12 ms for XLA's), and a single kernel program (16 samples) alone takes 0.53 ms: each
program walks ~100 dependent (load a weight block, multiply) steps with no
software pipelining, so its time is latency, not arithmetic or bandwidth. The way on is the
standard pipelined form: a ``fori_loop`` over each layer's weight tiles with ``num_stages`` > 1
(activations staged through memory), or a Mosaic GPU kernel whose weights stream by TMA.
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

CHUNK = 64  # widest block of a feature dimension
ROWS = 16  # samples per kernel program (Triton's smallest matrix-product tile)
WARPS = 4  # warps per kernel program
DTYPE = jnp.float32  # the matrix products' inputs (accumulation is float32)

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
    """A feature dimension of ``size`` cut into ``n`` chunks of width ``chunk`` (padded)."""

    size: int
    chunk: int
    n: int

    @classmethod
    def of(cls, size: int) -> "_Dim":
        chunk = min(CHUNK, max(16, 1 << (size - 1).bit_length()))
        return cls(size, chunk, -(-size // chunk))

    @property
    def padded(self) -> int:
        return self.chunk * self.n

    def cols(self, i: int) -> slice:
        return slice(i * self.chunk, (i + 1) * self.chunk)


def _pad_cols(x: jax.Array, dim: _Dim) -> jax.Array:
    return jnp.pad(x, [(0, 0)] * (x.ndim - 1) + [(0, dim.padded - x.shape[-1])])


def _pad_weight(w: jax.Array, din: _Dim, dout: _Dim) -> jax.Array:
    return jnp.pad(w, [(0, din.padded - w.shape[0]), (0, dout.padded - w.shape[1])])


def _load(ref, dim: _Dim) -> list:
    return [ref[:, dim.cols(i)] for i in range(dim.n)]


def _store(ref, chunks: list, dim: _Dim) -> None:
    for i, c in enumerate(chunks):
        ref[:, dim.cols(i)] = c


def _dot(a, b):
    return jnp.dot(a.astype(DTYPE), b, preferred_element_type=jnp.float32)


def _dot_t(a, b):
    """``a @ b.T``."""
    return jax.lax.dot_general(a.astype(DTYPE), b, (((1,), (1,)), ((), ())),
                               preferred_element_type=jnp.float32)


def _matmul(h: list, w_ref, din: _Dim, dout: _Dim) -> list:
    """``h @ W`` chunk by chunk: output chunk j = sum_i h_i W[i, j]."""
    out = []
    for j in range(dout.n):
        acc = None
        for i in range(din.n):
            p = _dot(h[i], w_ref[din.cols(i), dout.cols(j)])
            acc = p if acc is None else acc + p
        out.append(acc)
    return out


def _matmul_t(g: list, w_ref, din: _Dim, dout: _Dim) -> list:
    """``g @ W^T``: input chunk i = sum_j g_j W[i, j]^T."""
    out = []
    for i in range(din.n):
        acc = None
        for j in range(dout.n):
            p = _dot_t(g[j], w_ref[din.cols(i), dout.cols(j)])
            acc = p if acc is None else acc + p
        out.append(acc)
    return out


def _add_bias(z: list, b_ref, dim: _Dim) -> list:
    return [zj + b_ref[:, dim.cols(j)] for j, zj in enumerate(z)]


def _kernel(mode: str, dims: tuple[_Dim, ...], nfe: int = 0) -> Callable:
    """The kernel body of one mode; ``dims`` are the layers' feature dimensions, input first
    (for ``flow``: the latent's, then the hidden and output ones)."""
    n_layers = len(dims) - 1

    def forward(h, refs, tangent=None):
        """The network on chunks ``h``; returns outputs, pre-activations and the tangent."""
        pre = []
        for k in range(n_layers):
            w_ref, b_ref = refs[2 * k], refs[2 * k + 1]
            z = _add_bias(_matmul(h, w_ref, dims[k], dims[k + 1]), b_ref, dims[k + 1])
            if tangent is not None:
                tangent = _matmul(tangent, w_ref, dims[k], dims[k + 1])
            if k < n_layers - 1:
                pre.append(z)
                if tangent is not None:
                    tangent = [_silu_grad(zj) * tj for zj, tj in zip(z, tangent)]
                z = [_silu(zj) for zj in z]
            h = z
        return h, pre, tangent

    if mode == "jvp":
        def kernel(x_ref, t_ref, *refs):
            weights, (y_ref, yt_ref) = refs[:-2], refs[-2:]
            y, _, yt = forward(_load(x_ref, dims[0]), weights, _load(t_ref, dims[0]))
            _store(y_ref, y, dims[-1])
            _store(yt_ref, yt, dims[-1])
    elif mode == "vjp":
        def kernel(x_ref, g_ref, *refs):
            weights, gx_ref = refs[:-1], refs[-1]
            _, pre, _ = forward(_load(x_ref, dims[0]), weights)
            g = _load(g_ref, dims[-1])
            for k in reversed(range(n_layers)):
                g = _matmul_t(g, weights[2 * k], dims[k], dims[k + 1])
                if k > 0:
                    g = [gj * _silu_grad(zj) for gj, zj in zip(g, pre[k - 1])]
            _store(gx_ref, g, dims[0])
    elif mode == "flow":
        # refs: z0, c | W_z, W_c, time rows (the time embedding's product plus the first bias,
        # one row per Euler step), then the later layers' (W, b) | out. dims: (latent, context,
        # hidden..., output == latent)
        dz, dc, hidden = dims[0], dims[1], dims[2:]

        def kernel(z_ref, c_ref, wz_ref, wc_ref, tb_ref, *refs):
            weights, out_ref = refs[:-1], refs[-1]
            z = _load(z_ref, dz)
            context = _matmul(_load(c_ref, dc), wc_ref, dc, hidden[0])
            for i in range(nfe):
                h = [cj + zj + tb_ref[i:i + 1, hidden[0].cols(j)] for j, (cj, zj) in
                     enumerate(zip(context, _matmul(z, wz_ref, dz, hidden[0])))]
                for k in range(len(hidden) - 1):
                    h = [_silu(hj) for hj in h]
                    h = _add_bias(_matmul(h, weights[2 * k], hidden[k], hidden[k + 1]),
                                  weights[2 * k + 1], hidden[k + 1])
                z = [zj + hj / nfe for zj, hj in zip(z, h)]
            _store(out_ref, z, dz)
    else:
        raise ValueError(f"unknown kernel mode {mode!r}")
    return kernel


def _pallas(kernel: Callable, rows: list[jax.Array], consts: list[jax.Array],
            out_cols: list[int]) -> list[jax.Array]:
    """Runs ``kernel`` over blocks of ``ROWS`` rows of ``rows`` (each ``[B, cols]``), with
    ``consts`` (weights) whole; returns the outputs ``[B, c]`` for ``c`` in ``out_cols``."""
    from jax.experimental import pallas as pl
    from jax.experimental.pallas import triton as pl_triton

    batch = rows[0].shape[0]
    padded = -(-batch // ROWS) * ROWS
    rows = [jnp.pad(r, ((0, padded - batch), (0, 0))) for r in rows]
    consts = [c.reshape(1, -1) if c.ndim == 1 else c for c in consts]
    row_spec = lambda cols: pl.BlockSpec((ROWS, cols), lambda i: (i, 0))
    outs = pl.pallas_call(
        kernel,
        out_shape=[jax.ShapeDtypeStruct((padded, c), jnp.float32) for c in out_cols],
        grid=(padded // ROWS,),
        in_specs=[row_spec(r.shape[1]) for r in rows]
        + [pl.BlockSpec(c.shape, lambda i: (0, 0)) for c in consts],
        out_specs=[row_spec(c) for c in out_cols],
        interpret=_INTERPRET.get(),
        compiler_params=pl_triton.CompilerParams(num_warps=WARPS, num_stages=1),
        name="stride_fused_mlp",
    )(*rows, *consts)
    return [o[:batch] for o in outs]


def _padded_layers(layers, dims):
    out = []
    for (w, b), din, dout in zip(layers, dims[:-1], dims[1:]):
        out += [_pad_weight(w, din, dout).astype(DTYPE), _pad_cols(b, dout)]
    return out


def _dims(layers) -> tuple[_Dim, ...]:
    return tuple(_Dim.of(n) for n in [layers[0][0].shape[0]] + [w.shape[1] for w, _ in layers])


def _jvp_kernel(layers, x, t):
    dims = _dims(layers)
    y, yt = _pallas(_kernel("jvp", dims), [_pad_cols(x, dims[0]), _pad_cols(t, dims[0])],
                    _padded_layers(layers, dims), [dims[-1].padded] * 2)
    return y[:, :dims[-1].size], yt[:, :dims[-1].size]


def _vjp_kernel(layers, x, g):
    dims = _dims(layers)
    (gx,) = _pallas(_kernel("vjp", dims), [_pad_cols(x, dims[0]), _pad_cols(g, dims[-1])],
                    _padded_layers(layers, dims), [dims[0].padded])
    return gx[:, :dims[0].size]


def _flow_kernel(layers, z, c, nfe, time_features):
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
    consts = [_pad_weight(w_z, dz, hidden[0]).astype(DTYPE),
              _pad_weight(w_c, dc, hidden[0]).astype(DTYPE), time_rows]
    consts += _padded_layers(rest, hidden)
    (out,) = _pallas(_kernel("flow", (dz, dc) + hidden, nfe),
                     [_pad_cols(z, dz), _pad_cols(c, dc)], consts, [dz.padded])
    return out[:, :nz]


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


_jvp = _batched(_jvp_kernel, _jvp_ref, 2)
_vjp = _batched(_vjp_kernel, _vjp_ref, 1)


def jvp(params: dict, x: jax.Array, t: jax.Array) -> tuple[jax.Array, jax.Array]:
    """``(f(x), df(x) t)`` of an :func:`mlp.mlp` network with ``params``; ``x, t [din]``."""
    return _jvp(_layers(params), x, t)


def vjp(params: dict, x: jax.Array, g: jax.Array) -> jax.Array:
    """``df(x)^T g`` ``[din]`` of an :func:`mlp.mlp` network, ``g [dout]``."""
    return _vjp(_layers(params), x, g)


def flow_euler(params: dict, z0: jax.Array, context: jax.Array, nfe: int,
               time_features: int) -> jax.Array:
    """A flow-matching sample ``[dim]`` from ``z0 [dim]``: :func:`flow.integrate` with Euler
    steps, the vector field's ``params`` and its input ``(z, time embedding, context)``."""
    if nfe < 1:
        raise ValueError(f"flow_euler needs nfe >= 1, got {nfe}")
    f = _batched(lambda layers, z, c: _flow_kernel(layers, z, c, nfe, time_features),
                 lambda layers, z, c: _flow_ref(layers, z, c, nfe, time_features), 1)
    return f(_layers(params), z0, context)


__all__ = ["jvp", "vjp", "flow_euler", "interpret"]
