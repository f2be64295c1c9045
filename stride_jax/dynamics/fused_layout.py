"""Static sizes and index tables of :mod:`stride_jax.dynamics.fused_step`'s kernel for one
robot (numpy only, built once per model)."""

from __future__ import annotations

import dataclasses

import numpy as np

# The prologue's per-program scratch row: its segments, ``n`` columns each (nv padded).
PREP = ("qd_n", "tau_n", "rot", "rot_t", "q", "qd", "extra", "zero")


@dataclasses.dataclass(frozen=True)
class Layout:
    """Static sizes and index tables of one robot's step kernel.

    Entry slots (the network's outputs, padded to ``entries``): ``0 .. n_out - 1`` L's learned
    entries (row-major lower triangle of rows 3..nv-1), ``n_out`` V, ``n_out + 1`` the base's
    fixed ``sqrt(m)``, ``n_out + 2`` zero (L above its diagonal, padding).
    """

    nv: int
    n: int  # nq = nv + 1 padded
    nr: int  # nv - 3 padded: the reduced system without the base's translation
    n_out: int
    entries: int  # padded slots
    index: np.ndarray  # [n, n] the slot of L[i, j]
    index_r: np.ndarray  # [n, nr] the slots of column k of L's rows 3.. (row k)
    entry_row: np.ndarray  # [entries] i of each learned slot's L[i, j]
    entry_col: np.ndarray  # [entries] j
    diag: np.ndarray  # [entries] 1 where the slot is a learned diagonal entry (softplus)
    learned: np.ndarray  # [entries] 1 for L's learned entries
    feature_of_dof: np.ndarray  # [n] the feature column of each joint dof
    # the prologue's scratch row (``PREP``) and what the kernel gathers from it
    x_index: np.ndarray  # [nf padded] the prior's features: rotation matrix, joint angles
    t_index: np.ndarray  # [nf padded] their tangent along qd
    c_index: np.ndarray  # [nc padded] the flow's context (height, rotation, joints, qd, tau)
    qpos_of_dof: np.ndarray  # [n] a dof's coordinate (joints; 0 for the base)
    dof_of_qpos: np.ndarray  # [nq padded] a coordinate's dof (position, joints)
    act_of_dof: np.ndarray  # [n] the actuator driving a dof (0 where none: its gains are 0)
    prep: dict  # segment name -> first column in the scratch row

    @classmethod
    def of(cls, nv: int, act_dof: tuple[int, ...] = ()) -> "Layout":
        pow2 = lambda k: max(16, 1 << (k - 1).bit_length())
        n, nr = pow2(nv + 1), pow2(nv - 3)  # n: room for the configuration's nq = nv + 1
        rows, cols = np.tril_indices(nv)
        keep = rows >= 3
        rows, cols = rows[keep], cols[keep]
        n_out = len(rows)
        entries = pow2(n_out + 3)
        root, zero = n_out + 1, n_out + 2
        index = np.full((n, n), zero, np.int32)
        index[rows, cols] = np.arange(n_out)
        index[np.arange(3), np.arange(3)] = root
        index_r = np.full((n, nr), zero, np.int32)
        index_r[:nv, :nv - 3] = index[3:nv, :nv].T
        entry_row = np.zeros(entries, np.int32)
        entry_col = np.zeros(entries, np.int32)
        entry_row[:n_out], entry_col[:n_out] = rows, cols
        diag = np.zeros(entries, np.float32)
        diag[np.flatnonzero(rows == cols)] = 1.0
        learned = np.zeros(entries, np.float32)
        learned[:n_out] = 1.0
        feature_of_dof = np.zeros(n, np.int32)
        feature_of_dof[6:nv] = 9 + np.arange(nv - 6)  # features: rotation (9), then joints
        nj, nq = nv - 6, nv + 1
        nf, nc = 9 + nj, 1 + 9 + nj + 2 * nv
        P = {name: i * n for i, name in enumerate(PREP)}
        x_index = np.full(pow2(nf), P["zero"], np.int32)
        x_index[:9] = P["rot"] + np.arange(9)
        x_index[9:nf] = P["q"] + 7 + np.arange(nj)
        t_index = np.full(pow2(nf), P["zero"], np.int32)
        t_index[:9] = P["rot_t"] + np.arange(9)
        t_index[9:nf] = P["qd"] + 6 + np.arange(nj)
        c_index = np.full(pow2(nc), P["zero"], np.int32)
        c_index[:nc] = np.concatenate([[P["q"] + 2], x_index[:nf], P["qd_n"] + np.arange(nv),
                                       P["tau_n"] + np.arange(nv)])
        qpos_of_dof = np.zeros(n, np.int32)
        qpos_of_dof[6:nv] = 7 + np.arange(nj)
        dof_of_qpos = np.zeros(n, np.int32)
        dof_of_qpos[:3] = np.arange(3)
        dof_of_qpos[7:nq] = 6 + np.arange(nj)
        act_of_dof = np.zeros(n, np.int32)
        act_of_dof[list(act_dof)] = np.arange(len(act_dof))
        return cls(nv, n, nr, n_out, entries, index, index_r, entry_row, entry_col, diag,
                   learned, feature_of_dof, x_index, t_index, c_index, qpos_of_dof, dof_of_qpos,
                   act_of_dof, P)
