"""The linear probe: how much systematic structure a residual holds, cheaply.

A ridge regression of the (scaled one-step or k-step) residual on state, command and contact
features, fitted on the training split and scored held-out. The diagnosis uses it for the
*decision*: whether a significant gap exists at all (on the nominal residual) and whether the best
library hypothesis leaves enough structure to call the gap "unexplained by the library" (on the
residual after the best). What that structure is and where it lives is answered by the STRIDE
residual fitted on top (:mod:`stride_jax.gap.residual`), not by the probe.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from stride_jax.gap import fit, regions
from stride_jax.sim.model import SimModel



def features(sm: SimModel, data: fit.Data) -> np.ndarray:
    """``[M, F]`` state, command and contact features of each replayed sample."""
    idx = fit.samples_before_next(data)
    q, qd, u = data.q[idx], data.qd[idx], data.cmd[idx]
    qa = q[:, sm.mj.jnt_qposadr[sm.mj.actuator_trnid[:, 0]]]
    va = qd[:, sm.act_dof]
    prev = data.cmd[np.maximum(idx - 1, data.first)]
    f = [np.ones((len(idx), 1)), qa, np.sin(qa), np.cos(qa), va, np.tanh(va / 0.1), va * np.abs(va),
         u - (qa if sm.robot.kp is not None else 0.0), u - prev]
    if sm.robot.floating_base:
        f += [q[:, 2:7], qd[:, :6]]
    if sm.nfeet:
        ph = regions.sample_phases(sm, data)
        f += [(ph == k).astype(float) for k in range(4)]
    return np.concatenate(f, 1)


FEATURE_GROUPS = ("intercept", "joint position", "sin(position)", "cos(position)", "joint velocity",
                  "sign(velocity)", "velocity|velocity|", "command - position", "command change",
                  "base pose", "base velocity", "swing", "stance", "touchdown", "liftoff")


def structure_hints(sm: SimModel, train: fit.Data, r_train: np.ndarray, test: fit.Data,
                    r_test: np.ndarray, top: int = 3) -> list[dict[str, Any]]:
    """Which feature group (:data:`FEATURE_GROUPS`) of the linear probe, alone, explains most of the
    held-out residual left after the best hypothesis (e.g. ``velocity|velocity|`` for a quadratic
    drag fitted with linear damping): ``[{"feature", "explained"}]``, best first."""
    Xtr, Xte = features(sm, train), features(sm, test)
    nu = len(sm.act_dof)
    sizes = [1] + [nu] * 8 + ([5, 6] if sm.robot.floating_base else []) + ([sm.nfeet] * 4 if sm.nfeet else [])
    names = list(FEATURE_GROUPS[:9]) + (list(FEATURE_GROUPS[9:11]) if sm.robot.floating_base else []) + (
        list(FEATURE_GROUPS[11:]) if sm.nfeet else [])
    g = float((r_test ** 2).sum())
    out, i = [], 0
    for name, k in zip(names, sizes):
        cols = [0] + list(range(i, i + k)) if i else [0]
        i += k
        if name == "intercept":
            continue
        a, b = Xtr[:, cols], Xte[:, cols]
        mu, sd = a.mean(0), a.std(0)
        sd[sd < 1e-9] = 1.0
        mu[0], sd[0] = 0.0, 1.0
        a, b = (a - mu) / sd, (b - mu) / sd
        W = np.linalg.solve(a.T @ a + 1e-3 * len(a) * np.eye(len(cols)), a.T @ r_train)
        out.append({"feature": name, "explained": float(1 - ((r_test - b @ W) ** 2).sum() / max(g, 1e-300))})
    return sorted(out, key=lambda d: -d["explained"])[:top]


def probe(sm: SimModel, train: fit.Data, r_train: np.ndarray, test: fit.Data, r_test: np.ndarray,
          ridge: float = 1e-3) -> np.ndarray:
    """Held-out residual ``[M_test, nv]`` after a ridge regression on :func:`features` fitted on
    the training residual (features standardised on train)."""
    Xtr, Xte = features(sm, train), features(sm, test)
    mu, sd = Xtr.mean(0), Xtr.std(0)
    sd[sd < 1e-9] = 1.0
    mu[0], sd[0] = 0.0, 1.0  # intercept
    Xtr, Xte = (Xtr - mu) / sd, (Xte - mu) / sd
    A = Xtr.T @ Xtr + ridge * len(Xtr) * np.eye(Xtr.shape[1])
    W = np.linalg.solve(A, Xtr.T @ r_train)
    return r_test - Xte @ W
