"""A STRIDE model step as one Pallas (Triton) kernel: a planner's horizon step on a GPU in ~10
launches where XLA makes ~57 and the per-pass kernels ~32 (``results/mppi_latency/README.md``, sessions 7-8).

For a floating-base robot with position servos integrated implicitly, one network for L and V
(``StructuredConfig.shared_lnn``) and a flow residual sampled with Euler steps, one kernel
program takes a block of 8 or 16 samples ``(q, qd, ctrl, z)`` (``program_rows``) through

0. the servo at the next state (``Actuation.implicit``), the prior's features (rotation matrix,
   joint angles) and their tangent along ``qd``, and the flow's context;
1. the prior's network forward and along the tangent (L, its rate, V);
2. the products with L (``u = L^T v``, ``M v``, ``dM/dt v``), the cotangent of the kinetic
   energy on L's entries, the network's transposed pass and the features' transposed Jacobian
   (joints, and the body rotation's ``vee(skew(R^T G))``), then ``omega x p_omega``;
3. the flow's ``nfe`` Euler steps from the latent ``z`` given the context;
4. the solve with ``M + diag(servo)``: L's first rows are ``sqrt(m) I``, so the base's
   translation eliminates exactly and a Cholesky factorisation of the rest (15 x 15 for Go1)
   runs in registers;
5. semi-implicit Euler with the quaternion's exponential map,

and writes ``(q', qd')``. XLA keeps the random draws and the planner's cost. Written for one
example like the rest of the library: under ``vmap`` on a GPU it is one kernel for the batch
(``jax.custom_batching.custom_vmap``); on a CPU, and unbatched, it is the XLA step it
replaces (the kernel runs on a CPU only in Pallas' interpreter, which the tests use).

Layout inside a program (``fused_pallas`` has the network passes, ``fused_layout`` the index
tables): per-dof quantities are ``[rows, n]`` tensors (``n``: nq padded to a power of two); the
prologue writes its quantities into one scratch row (``PREP``) and the networks' inputs are
gathered from it through static index tables; L's entries stay in the network's output order in
a buffer, and L's rows and columns are gathered from it (``Layout.index``) inside short loops.

Measured (one H100, Go1 STRIDE NFE 2, K = 1024, H = 30, MPPI step; commands in
``results/mppi_latency/README.md``): 64 x 3 networks 2.80 ms (2.47 ms with bfloat16 products) against 6.27 ms
in XLA; 128 x 3 3.94 / 3.24 ms against 6.52; 256 x 3 8.19 / 4.21 against 7.57. Programs of 8
rows where 16 leave SMs idle (``program_rows``; one H200, bfloat16): Go1 64 x 3 2.63 -> 2.41 ms,
256 x 3 4.39 -> 3.70 ms, G1 64 x 3 7.99 -> 5.18 ms (XLA 8.78). In the version
before the prologue and integration moved in (64 x 3, leaving parts out: ``SKIP``) the solve
took ~24 us per step, the products and transposed pass ~22 us, the flow ~6 us. Unrolling the
small loops lets their loads issue ahead but Triton's compile time grows steeply (``UNROLL``;
the products' loops alone: -4% time, +11 s compile).
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import jax
import jax.numpy as jnp

from stride_jax.dynamics import fused_pallas as fp
from stride_jax.dynamics.fused_layout import PREP, Layout
from stride_jax.dynamics.time_embedding import time_embedding

WARPS = 8  # warps per program of the step kernel (the reduced mass matrix in registers)
# Samples per program: None lets ``program_rows`` choose; an int fixes it (the probes' --rows).
ROWS: int | None = None
# Parts left out, to time the others (``experiments/probes/fused_step_check.py --skip``; wrong results):
# "products" (L's products and the transposed pass), "flow", "solve".
SKIP: frozenset = frozenset()
# The small loops unrolled, by name ("products", "gram", "factor", "backward"). Unrolled, a loop's
# loads are issued ahead; but Triton's compile time grows steeply (all four unrolled: > 2 min).
UNROLL: frozenset = frozenset()
# Columns per iteration of the small loops, by name (the same names; 1 where not given): a loop
# of ``n`` steps becomes ``n // b`` iterations of ``b`` columns and a last one of the rest. In
# the factorisation a block's ``b`` columns are read from the reduced matrix at once and the
# matrix takes one rank-``b`` update, and the backward substitution takes a block's products with
# the solved rows at once: fewer dependent round trips through the ``[rows, nr, nr]`` register
# tensor, the same arithmetic. One H200, G1 64 x 3, K = 1024: blocks of 4 in every loop 175.0
# against 190.4 us per rollout step (``results/mppi_latency/README.md``, session 79); the planner
# end to end (one H100, K = 1024, H = 30, bfloat16, session 83): G1 64 x 3 4.84 -> 4.60 ms, Go1
# 256 x 3 3.41 -> 3.29 ms (blocking the factorisation and the substitution alone: 4.84). The
# default since; ``{}`` (or the probes' ``--block 1``) is the kernel before.
BLOCK: dict = dict.fromkeys(("products", "gram", "factor", "backward"), 4)
# The reduced system factorised in two halves where its columns fill more than half its padded
# size (``_factor_split``; G1: 32 of 32, Go1: 15 of 16): each half's rank-one updates on a tensor
# of the size it needs. The planner end to end (one H100, K = 1024, H = 30, bfloat16, session 84):
# G1 64 x 3 4.94 -> 4.06 ms, Go1 256 x 3 3.72 -> 3.48 ms, Go1 64 x 3 2.07 -> 2.02 ms. ``False``
# (the probes' ``--split 0``): one factorisation of all of it, the kernel before.
SPLIT: bool = True


def program_rows(batch: int, sms: int | None = None) -> int:
    """Samples per program for a batch of ``batch``: the fewest waves of programs over the GPU's
    ``sms`` multiprocessors (one program per SM: the kernel's 255 registers per thread allow no
    second), then 8 rows rather than 16. A program's time is latency, not arithmetic: 8 rows take
    87% of 16 rows' time (one H200, Go1 64 x 3 and 256 x 3 at K = 1024: 104 -> 90 and 171 -> 148
    us per rollout step; 4 rows: 137 and 233), so halving the rows pays only where the programs
    would otherwise leave SMs idle (K = 1024: 64 programs of 16 on 132 SMs) and not where it adds
    a wave. ``sms`` defaults to the default device's (16 rows where it reports none: a CPU, the
    interpreter)."""
    if ROWS:
        return ROWS
    if sms is None:
        sms = getattr(jax.devices()[0], "core_count", None)
    if not sms:
        return fp.ROWS
    ceil = lambda a, b: -(-a // b)
    waves = lambda rows: ceil(ceil(batch, rows), sms)
    return 8 if waves(8) <= waves(fp.ROWS) else fp.ROWS


def _col(x, i):
    """Column ``i`` ``[R, 1]`` of a register tensor ``x [R, c]`` (``i`` static or traced)."""
    cols = jax.lax.broadcasted_iota(jnp.int32, x.shape, 1)
    return jnp.sum(jnp.where(cols == i, x, 0.0), axis=1, keepdims=True)


def _set(x, i, value):
    cols = jax.lax.broadcasted_iota(jnp.int32, x.shape, 1)
    return jnp.where(cols == i, value, x)


def _gather(ref, index):
    """``ref[r, index[r, c]]`` for a row block ``ref [R, .]`` and ``index [1 or R, c]``."""
    shape = (ref.shape[0], index.shape[-1])
    rows = jax.lax.broadcasted_iota(jnp.int32, shape, 0)
    return ref[rows, jnp.broadcast_to(index, shape)]


def _loop(name: str, n: int, body: Callable, init):
    """``body(i, carry)`` for ``i < n``: as a loop, or unrolled if ``name`` is in ``UNROLL``."""
    if name not in UNROLL:
        return jax.lax.fori_loop(0, n, body, init)
    for i in range(n):
        init = body(i, init)
    return init


def _blocks(name: str, n: int, body: Callable, init, reverse: bool = False):
    """``body(start, width, carry)`` over the steps ``0 .. n - 1`` in blocks of ``BLOCK[name]``
    (``width`` static, ``start`` traced inside the loop): the full blocks as one loop (``_loop``),
    then the rest as one more block; ``reverse`` from the last step down (the rest last, at 0)."""
    width = max(1, min(int(BLOCK.get(name, 1)), n))
    full, rest = divmod(n, width)
    start = (lambda i: n - (i + 1) * width) if reverse else (lambda i: i * width)
    carry = _loop(name, full, lambda i, c: body(start(i), width, c), init)
    return body(0 if reverse else full * width, rest, carry) if rest else carry


def _kernel(lay: Layout, lnn_dims, flow_dims, nfe: int, floor: float, dt: float,
            rows: int) -> Callable:
    """The kernel body for programs of ``rows`` samples; ``lnn_dims``: the prior network's
    feature dimensions (input first), ``flow_dims``: the flow's (latent, context, then its
    layers' outputs)."""
    n_l = len(lnn_dims) - 1
    n_fw = 2 * (len(flow_dims) - 3)
    R, n, nv, P = rows, lay.n, lay.nv, lay.prep

    def kernel(q_ref, qd_ref, ctrl_ref, z_ref, *refs):
        w_lnn, refs = refs[:2 * n_l], refs[2 * n_l:]
        wz_ref, wc_ref, tb_ref, refs = refs[0], refs[1], refs[2], refs[3:]
        w_flow, refs = refs[:n_fw], refs[n_fw:]
        (index_ref, index_t_ref, index_r_ref, erow_ref, ecol_ref, diag_ref, learned_ref,
         fixed_ref, fdof_ref, force_ref, mass_ref, x_index_ref, t_index_ref, c_index_ref,
         qpos_ref, dof_of_qpos_ref, act_ref, servo_ref), refs = refs[:18], refs[18:]
        (q_out, qd_out, a0, a1, t0, t1, raw_ref, rawt_ref, ent_ref, dent_ref, uw_ref, p_ref,
         gx_ref, vec_ref, cw, chol_ref, prep_ref), zs = refs[:17], refs[17:]
        dof = jax.lax.broadcasted_iota(jnp.int32, (R, n), 1)

        # 0. the servo at the next state (Actuation.implicit), the features, their tangent and
        # the flow's context, through the scratch row
        q, qd = fp._load_in(q_ref, nv + 1), fp._load_in(qd_ref, nv)
        kp, kd, lo, hi, limited, inv_qd, inv_tau = (servo_ref[i:i + 1, :] for i in range(7))
        qj, cj = _gather(q_ref, qpos_ref[...]), _gather(ctrl_ref, act_ref[...])
        raw_servo = kp * (cj - qj) - kd * qd
        tau = jnp.where(limited > 0, jnp.clip(raw_servo, lo, hi), raw_servo)
        free = (limited == 0) | ((raw_servo >= lo) & (raw_servo <= hi))
        tau0 = jnp.where(free, kp * (cj - qj - dt * qd) - kd * qd, tau)
        extra = jnp.where(free, kp * dt * dt + kd * dt, 0.0)
        w_, x_, y_, z_ = (q_ref[:, k:k + 1] for k in range(3, 7))
        rot = [[1 - 2 * (y_ * y_ + z_ * z_), 2 * (x_ * y_ - w_ * z_), 2 * (x_ * z_ + w_ * y_)],
               [2 * (x_ * y_ + w_ * z_), 1 - 2 * (x_ * x_ + z_ * z_), 2 * (y_ * z_ - w_ * x_)],
               [2 * (x_ * z_ - w_ * y_), 2 * (y_ * z_ + w_ * x_), 1 - 2 * (x_ * x_ + y_ * y_)]]
        om = [qd_ref[:, k:k + 1] for k in range(3, 6)]
        rot_row = rot_t_row = jnp.zeros((R, n), jnp.float32)
        for a in range(3):
            for b in range(3):  # (R [omega]x)_ab = R_a,b+1 omega_b+2 - R_a,b+2 omega_b+1
                b1, b2 = (b + 1) % 3, (b + 2) % 3
                rot_row = _set(rot_row, 3 * a + b, rot[a][b])
                rot_t_row = _set(rot_t_row, 3 * a + b, rot[a][b1] * om[b2] - rot[a][b2] * om[b1])
        for name, value in [("qd_n", qd * inv_qd), ("tau_n", tau * inv_tau), ("rot", rot_row),
                            ("rot_t", rot_t_row), ("q", q), ("qd", qd), ("extra", extra),
                            ("zero", jnp.zeros((R, n), jnp.float32))]:
            prep_ref[:, P[name]:P[name] + n] = value
        fp._barrier()
        x, t = _gather(prep_ref, x_index_ref[...]), _gather(prep_ref, t_index_ref[...])
        c = _gather(prep_ref, c_index_ref[...])
        r0 = tau0 - jnp.where(dof == 2, mass_ref[:, 4:5], 0.0)  # m g along world z

        # 1. the prior's network forward and along the tangent; L's entries and their rates
        fp._forward(lnn_dims, w_lnn, x, (a0, a1, t0, t1), (raw_ref, rawt_ref), t, zs)
        raw, raw_t = raw_ref[...], rawt_ref[...]
        diag, learned = diag_ref[...], learned_ref[...]
        sig = jax.nn.sigmoid(raw)
        ent_ref[...] = learned * jnp.where(diag > 0, jax.nn.softplus(raw), raw) + fixed_ref[...]
        dent_ref[...] = learned * jnp.where(diag > 0, sig * raw_t, raw_t)
        fp._barrier()

        # 2. products with L (rows and columns gathered from the entries) and the bias force
        bias = jnp.zeros((R, n), jnp.float32)
        if "products" not in SKIP:
            def by_rows(i0, width, uw):  # u = L^T v, w = dL^T v
                for i in (i0 + t for t in range(width)):
                    vi = qd_ref[:, _ds(i)]
                    row = index_ref[_ds(i), :]
                    uw = uw[0] + vi * _gather(ent_ref, row), uw[1] + vi * _gather(dent_ref, row)
                return uw

            zero = jnp.zeros((R, n), jnp.float32)
            u, w = _blocks("products", nv, by_rows, (zero, zero))
            uw_ref[:, :n], uw_ref[:, n:] = u, w
            fp._barrier()

            def by_cols(j0, width, pm):  # p = L u, dM/dt v = dL u + L w
                for j in (j0 + t for t in range(width)):
                    col = index_t_ref[_ds(j), :]
                    lc, dlc = _gather(ent_ref, col), _gather(dent_ref, col)
                    uj, wj = uw_ref[:, _ds(j)], uw_ref[:, _ds(n + j)]
                    pm = pm[0] + uj * lc, pm[1] + uj * dlc + wj * lc
                return pm

            p, mdot_v = _blocks("products", nv, by_cols, (zero, zero))
            p = p + floor * qd
            p_ref[...] = p
            # cotangent of 1/2 |L^T v|^2 on L's entries (v_i u_j, through softplus on the
            # diagonal) and -1 on V; then the network's transposed pass
            g = learned * _gather(qd_ref, erow_ref[...]) * _gather(uw_ref, ecol_ref[...])
            g = g * jnp.where(diag > 0, sig, 1.0)
            slot = jax.lax.broadcasted_iota(jnp.int32, g.shape, 1)
            g = jnp.where(slot == lay.n_out, -1.0, g)
            fp._transposed(lnn_dims, w_lnn, zs, g, gx_ref, (a0, a1), rawt_ref)
            # dL/d(delta): joints read their features; the rotation is vee(skew(R^T G)), G the
            # cotangent of the rotation matrix's features (row-major, the first nine)
            dl_dq = jnp.where((dof >= 6) & (dof < nv), _gather(gx_ref, fdof_ref[...]), 0.0)

            def skew_part(i, j):  # (R^T G)_ij - (R^T G)_ji
                gx = lambda a, b: gx_ref[:, 3 * a + b:3 * a + b + 1]
                return sum(rot[a][i] * gx(a, j) - rot[a][j] * gx(a, i) for a in range(3))

            for axis, (i, j) in enumerate([(2, 1), (0, 2), (1, 0)]):
                dl_dq = _set(dl_dq, 3 + axis, skew_part(i, j))
            cross = jnp.zeros((R, n), jnp.float32)  # the body rotation's omega x p_omega
            for a in range(3):
                i1, i2 = 3 + (a + 1) % 3, 3 + (a + 2) % 3
                cross = _set(cross, 3 + a, qd_ref[:, i1:i1 + 1] * p_ref[:, i2:i2 + 1]
                             - qd_ref[:, i2:i2 + 1] * p_ref[:, i1:i1 + 1])
            bias = mdot_v - dl_dq + cross

        # 3. the flow's sample from z given the context
        z = fp._load_in(z_ref, nv)
        if "flow" not in SKIP:
            z = fp._flow_steps(flow_dims, nfe, c, wz_ref, wc_ref, tb_ref, w_flow, cw, a0, a1, z)
        rhs = r0 - bias + force_ref[...] * z

        # 4. (M + diag(servo)) qdd = rhs
        qdd = rhs
        if "solve" not in SKIP:
            qdd = _solve(lay, floor, rhs, ent_ref, index_r_ref, mass_ref, prep_ref, vec_ref,
                         chol_ref)

        # 5. semi-implicit Euler: qd' = qd + dt qdd, then q' = q (+) dt qd' (integrate.retract)
        qd2 = jnp.where(dof < nv, qd + dt * qdd, 0.0)
        vec_ref[:, :n] = qd2
        fp._barrier()
        rv = [dt * _col(qd2, 3 + k) for k in range(3)]
        angle2 = rv[0] * rv[0] + rv[1] * rv[1] + rv[2] * rv[2]
        small = angle2 < 1e-12
        angle = jnp.sqrt(jnp.where(small, 1.0, angle2))
        half = 0.5 * jnp.where(small, 0.0, angle)
        scale = jnp.where(small, 0.5 - angle2 / 48.0, jnp.sin(half) / angle)
        bw, bv = jnp.cos(half), [scale * r for r in rv]
        av = [x_, y_, z_]
        quat = [w_ * bw - (av[0] * bv[0] + av[1] * bv[1] + av[2] * bv[2])]
        quat += [w_ * bv[k] + bw * av[k] + av[(k + 1) % 3] * bv[(k + 2) % 3]
                 - av[(k + 2) % 3] * bv[(k + 1) % 3] for k in range(3)]
        norm = jnp.sqrt(sum(e * e for e in quat))
        q2 = q + dt * _gather(vec_ref, dof_of_qpos_ref[...])
        for k in range(4):
            q2 = _set(q2, 3 + k, quat[k] / norm)
        fp._put(q_out, slice(0, n), q2, nv + 1)
        fp._put(qd_out, slice(0, n), qd2, nv)

    return kernel


def _solve(lay, floor, rhs, ent_ref, index_r_ref, mass_ref, prep_ref, vec_ref, chol_ref):
    """``(L L^T + floor I + diag(extra)) qdd = rhs``. L's first rows are sqrt(m) I, so the base's
    translation eliminates exactly (a Schur complement): ``S x2 = r2 - (s / a) B r1`` with
    ``S = (floor / a) B B^T + L22 L22^T + D2``, ``a = m + floor``, ``s = sqrt(m)``, B L's rows
    3.. and columns 0-2; then ``x1 = (r1 - s B^T x2) / a``. S is factorised right-looking in
    registers (in two parts where ``SPLIT``: ``_factor_split``), the forward substitution in the
    same loop, its columns kept for the backward one; each loop takes ``BLOCK[name]`` columns per
    iteration."""
    R, n, nr, nv, P = rhs.shape[0], lay.n, lay.nr, lay.nv, lay.prep
    m = nv - 3  # the reduced system's size (nr: padded)
    dof = jax.lax.broadcasted_iota(jnp.int32, (R, n), 1)
    vec_ref[:, :n] = rhs
    fp._barrier()
    s, f_a, s_a, inv_a = (mass_ref[:, k:k + 1] for k in range(4))
    red = jax.lax.broadcasted_iota(jnp.int32, (R, nr), 1)
    shift = jnp.minimum(jax.lax.broadcasted_iota(jnp.int32, (1, nr), 1) + 3, n - 1)
    r2 = jnp.where(red < m, _gather(vec_ref, shift), 0.0)
    d2 = jnp.where(red < m, floor + _gather(prep_ref, shift + P["extra"]), 0.0)
    base_cols = [_gather(ent_ref, index_r_ref[k:k + 1, :]) for k in range(3)]
    for k in range(3):
        r2 = r2 - s_a * _col(rhs, k) * base_cols[k]

    if SPLIT and m > nr // 2:
        y = _factor_split(lay, floor, f_a, d2, r2, base_cols, ent_ref, index_r_ref, prep_ref,
                          vec_ref, chol_ref)
    else:
        ii = jax.lax.broadcasted_iota(jnp.int32, (R, nr, nr), 1)
        jj = jax.lax.broadcasted_iota(jnp.int32, (R, nr, nr), 2)

        def gram(k0, width, S):  # L22's columns k: S += c c^T
            for k in (k0 + t for t in range(width)):
                col = _gather(ent_ref, index_r_ref[_ds(3 + k), :])
                S = S + col[:, :, None] * col[:, None, :]
            return S

        S = sum(f_a[:, :, None] * c[:, :, None] * c[:, None, :] for c in base_cols)
        S = S + jnp.where(ii == jj, d2[:, :, None], 0.0)
        S = _blocks("gram", m, gram, S)
        y = _factor(m, S, r2, chol_ref, nr, 0)
    fp._barrier()

    def backward(j0, width, x):  # the block's rows, from its last up
        cols = [chol_ref[:, _ds((j0 + t) * nr, nr)] for t in range(width)]
        below = [jnp.sum(jnp.where(red >= j0 + width, c * x, 0.0), axis=1, keepdims=True)
                 for c in cols]  # the rows solved before this block
        xs = [None] * width
        for t in reversed(range(width)):
            acc = _col(x, j0 + t) - below[t]
            for u in range(t + 1, width):
                acc = acc - _col(cols[t], j0 + u) * xs[u]
            xs[t] = acc / _col(cols[t], j0 + t)
        for t in range(width):
            x = jnp.where(red == j0 + t, xs[t], x)
        return x

    x2 = _blocks("backward", m, backward, y, reverse=True)
    vec_ref[:, n:n + nr] = x2
    fp._barrier()
    qdd = jnp.where((dof >= 3) & (dof < nv),
                    _gather(vec_ref, jnp.clip(jax.lax.broadcasted_iota(
                        jnp.int32, (1, n), 1) - 3, 0, nr - 1) + n), 0.0)
    for k in range(3):
        dot = jnp.sum(base_cols[k] * x2, axis=1, keepdims=True)
        qdd = _set(qdd, k, (_col(rhs, k) - s * dot) * inv_a)
    return qdd


def _factor(count, S, y, chol_ref, nr, off):
    """Right-looking Cholesky of the first ``count`` columns of ``S [R, r, c]`` with the forward
    substitution of ``y [R, r]``: the factor's column ``j`` goes to ``chol_ref``'s column
    ``off + j``, rows ``off ..`` (the reduced system's rows ``off .. off + r``; rows above
    ``off`` are not written: every reader, the backward substitution included, takes a
    column's rows from its own block down). ``c == r``: S is the whole symmetric matrix, updated by each column with
    itself. ``c < r``: S holds only the first ``c`` columns, and each block's columns update it
    with their first ``c`` rows read back from ``chol_ref`` (a barrier per block). ``y``'s
    solved entries returned."""
    R, r, c = S.shape
    red = jax.lax.broadcasted_iota(jnp.int32, (R, r), 1)
    jj = jax.lax.broadcasted_iota(jnp.int32, S.shape, 2)

    def body(j0, width, carry):
        S, y = carry
        cols = [jnp.sum(jnp.where(jj == j0 + t, S, 0.0), axis=2) for t in range(width)]
        done = []
        for t in range(width):  # the block's columns in turn, each on the later ones
            j = j0 + t
            root = jnp.sqrt(_col(cols[t], j))
            col = jnp.where(red >= j, cols[t], 0.0) / root
            chol_ref[:, _ds((off + j) * nr + off, r)] = col
            yj = _col(y, j) / root
            y = jnp.where(red > j, y - col * yj, jnp.where(red == j, yj, y))
            for u in range(t + 1, width):
                cols[u] = cols[u] - col * _col(col, j0 + u)
            if c == r:
                S = S - col[:, :, None] * col[:, None, :]
            done.append(col)
        if c < r:
            fp._barrier()
            for t, col in enumerate(done):
                top = chol_ref[:, _ds((off + j0 + t) * nr + off, c)]
                S = S - col[:, :, None] * top[:, None, :]
        return S, y

    return _blocks("factor", count, body, (S, y))[1]


def _factor_split(lay, floor, f_a, d2, r2, base_cols, ent_ref, index_r_ref, prep_ref, vec_ref,
                  chol_ref):
    """The reduced system's factorisation and forward substitution in two parts of ``h = nr /
    2`` columns, each on a tensor of the size it needs instead of all ``nr x nr`` for every
    column: (1) S's first ``h`` columns ``[R, nr, h]`` (L22 is lower triangular, so they take
    only L22's first ``h`` columns) factorised; (2) the trailing block ``[R, nr - h, nr - h]``
    built from L22's rows ``h ..``, less the first part's factor columns' rank-``h`` downdate,
    factorised. The rank-one updates' arithmetic falls by ~half (G1's 32 reduced dofs: ~35k
    against ~69k multiply-adds per sample) and the big register tensor is half the size. Returns
    ``y`` of all ``nr`` rows."""
    R, n, nr, P = r2.shape[0], lay.n, lay.nr, lay.prep
    m, h = lay.nv - 3, lay.nr // 2
    w = nr - h
    gather_cols = lambda k, lo, size: _gather(ent_ref, index_r_ref[_ds(k), _ds(lo, size)])

    # (1) S[:, :h]: the base's rank 3, D2, L22's first h columns
    ii = jax.lax.broadcasted_iota(jnp.int32, (R, nr, h), 1)
    jj = jax.lax.broadcasted_iota(jnp.int32, (R, nr, h), 2)
    tops = [gather_cols(k, 0, h) for k in range(3)]
    S = sum(f_a[:, :, None] * c[:, :, None] * t[:, None, :] for c, t in zip(base_cols, tops))
    S = S + jnp.where(ii == jj, d2[:, :, None], 0.0)

    def gram_left(k0, width, S):
        for k in (k0 + t for t in range(width)):
            col, top = gather_cols(3 + k, 0, nr), gather_cols(3 + k, 0, h)
            S = S + col[:, :, None] * top[:, None, :]
        return S

    S = _blocks("gram", h, gram_left, S)
    y = _factor(h, S, r2, chol_ref, nr, 0)
    vec_ref[:, n:n + nr] = y
    fp._barrier()

    # (2) the trailing block: the base's rank 3, D2, all of L22's columns on rows h.., less
    # the first part's factor columns on those rows; then its factorisation
    ii = jax.lax.broadcasted_iota(jnp.int32, (R, w, w), 1)
    jj = jax.lax.broadcasted_iota(jnp.int32, (R, w, w), 2)
    red = jax.lax.broadcasted_iota(jnp.int32, (R, w), 1)
    shift = jnp.minimum(jax.lax.broadcasted_iota(jnp.int32, (1, w), 1) + 3 + h, n - 1)
    d2_low = jnp.where(red < m - h, floor + _gather(prep_ref, shift + P["extra"]), 0.0)
    lows = [gather_cols(k, h, w) for k in range(3)]
    T = sum(f_a[:, :, None] * c[:, :, None] * c[:, None, :] for c in lows)
    T = T + jnp.where(ii == jj, d2_low[:, :, None], 0.0)

    def gram_low(k0, width, T):
        for k in (k0 + t for t in range(width)):
            col = gather_cols(3 + k, h, w)
            T = T + col[:, :, None] * col[:, None, :]
        return T

    def downdate(j0, width, T):
        for j in (j0 + t for t in range(width)):
            col = chol_ref[:, _ds(j * nr + h, w)]
            T = T - col[:, :, None] * col[:, None, :]
        return T

    T = _blocks("gram", m, gram_low, T)
    T = _blocks("gram", h, downdate, T)
    y_low = _factor(m - h, T, vec_ref[:, n + h:n + nr], chol_ref, nr, h)
    vec_ref[:, n + h:n + nr] = y_low
    fp._barrier()
    return vec_ref[:, n:n + nr]


def _ds(start, size=1):
    """``pl.ds``: a (possibly traced) slice of ``size`` from ``start``."""
    from jax.experimental import pallas as pl
    return pl.ds(start, size)


@dataclasses.dataclass(frozen=True)
class Static:
    """What the kernel needs besides arrays: the layout, the flow's budget and time features,
    the mass floor, the time step and the products' type."""

    layout: Layout
    nfe: int
    time_features: int
    floor: float
    dt: float
    dtype: object


def step_batched(st: Static, lnn_layers, flow_layers, sqrt_mass, gravity, servo, force_scale,
                 q, qd, ctrl, z):
    """``(q', qd')``: one semi-implicit Euler step of ``st.dt`` for each row of ``q [B, nq]``,
    ``qd [B, nv]``, ``ctrl [B, nu]`` and the flow's latent ``z [B, nv]``. ``servo [7, nv]``: the
    servo's ``kp, kd, lo, hi, limited`` per dof (zeros where no actuator drives it) and the
    context's ``1 / qd`` and ``1 / tau`` scales."""
    from jax.experimental import pallas as pl
    from jax.experimental.pallas import triton as pl_triton

    lay, dtype = st.layout, st.dtype
    n, nv, nz, tf = lay.n, lay.nv, lay.nv, st.time_features
    lnn_dims = fp._dims(lnn_layers)
    lnn_dims = lnn_dims[:-1] + (fp._Dim(lnn_dims[-1].size, lay.entries,
                                        min(fp.CHUNK, lay.entries)),)
    (w1, b1), rest = flow_layers[0], flow_layers[1:]
    dz = fp._Dim(nz, n, min(fp.CHUNK, n))
    dc = fp._Dim(w1.shape[0] - nz - tf, len(lay.c_index), min(fp.CHUNK, len(lay.c_index)))
    hidden = tuple(fp._Dim.of(w.shape[1]) for w, _ in flow_layers)
    hidden = hidden[:-1] + (dz,)
    w_z, w_t, w_c = w1[:nz], w1[nz:nz + tf], w1[nz + tf:]

    times = jnp.stack([time_embedding(i / st.nfe, tf) for i in range(st.nfe)])
    n_rows = 1 << (st.nfe - 1).bit_length()
    time_rows = jnp.pad(times @ w_t + b1, ((0, n_rows - st.nfe),
                                          (0, hidden[0].padded - b1.shape[0])))
    flow_consts = [fp._pad_weight(w_z, dz, hidden[0]).astype(dtype),
                   fp._pad_weight(w_c, dc, hidden[0]).astype(dtype), time_rows]
    flow_consts += fp._padded_layers(rest, hidden, dtype)
    fixed = jnp.zeros((1, lay.entries), jnp.float32).at[0, lay.n_out + 1].set(sqrt_mass)
    a = sqrt_mass ** 2 + st.floor
    mass = jnp.zeros((1, 16), jnp.float32).at[0, :5].set(
        jnp.stack([sqrt_mass, st.floor / a, sqrt_mass / a, 1.0 / a, gravity]))
    row = lambda x: jnp.asarray(x)[None]
    pad_n = lambda x: jnp.pad(jnp.asarray(x, jnp.float32),
                              [(0, 0)] * (jnp.ndim(x) - 1) + [(0, n - jnp.shape(x)[-1])])
    servo_rows = jnp.pad(pad_n(servo), ((0, 8 - servo.shape[0]), (0, 0)))
    tables = [jnp.asarray(lay.index), jnp.asarray(lay.index.T.copy()), jnp.asarray(lay.index_r),
              row(lay.entry_row), row(lay.entry_col), row(lay.diag), row(lay.learned), fixed,
              row(lay.feature_of_dof),
              pad_n(jnp.broadcast_to(jnp.asarray(force_scale, jnp.float32), (nz,)))[None], mass,
              row(lay.x_index), row(lay.t_index), row(lay.c_index), row(lay.qpos_of_dof),
              row(lay.dof_of_qpos), row(lay.act_of_dof), servo_rows]
    consts = fp._padded_layers(lnn_layers, lnn_dims, dtype) + flow_consts + tables
    consts = [x.reshape(1, -1) if x.ndim == 1 else x for x in consts]

    batch = q.shape[0]
    R = program_rows(batch)
    padded = -(-batch // R) * R
    rows = [jnp.pad(r, ((0, padded - batch), (0, 0))) for r in (q, qd, ctrl, z)]
    blocks = [n, n, max(16, 1 << (ctrl.shape[1] - 1).bit_length()), n]
    wide = max([d.padded for d in lnn_dims] + [d.padded for d in hidden])
    widths = ([wide] * 4 + [lay.entries] * 4 + [2 * n, n, lnn_dims[0].padded, n + lay.nr,
                                                 hidden[0].padded, lay.nr * lay.nr,
                                                 len(PREP) * n]
              + [d.padded for d in lnn_dims[1:-1]])
    row_spec = lambda cols: pl.BlockSpec((R, cols), lambda i: (i, 0))
    results = pl.pallas_call(
        _kernel(lay, lnn_dims, (dz, dc) + hidden, st.nfe, st.floor, st.dt, R),
        out_shape=[jax.ShapeDtypeStruct((padded, nv + 1), jnp.float32),
                   jax.ShapeDtypeStruct((padded, nv), jnp.float32)]
        + [jax.ShapeDtypeStruct((padded, w), jnp.float32) for w in widths],
        grid=(padded // R,),
        in_specs=[row_spec(b) for b in blocks]
        + [pl.BlockSpec(x.shape, lambda i: (0, 0)) for x in consts],
        out_specs=[row_spec(n), row_spec(n)] + [row_spec(w) for w in widths],
        interpret=fp._INTERPRET.get(),
        compiler_params=pl_triton.CompilerParams(num_warps=WARPS, num_stages=fp.STAGES),
        name="stride_fused_step",
    )(*rows, *consts)
    return results[0][:batch], results[1][:batch]

