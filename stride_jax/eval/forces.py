"""Contact forces from a generalised residual, and the residual's share of the acceleration.

A structured model predicts a generalised residual force ``eps [nv]`` (the paper's eps_CFM). At a
state where a set S of feet is in stance, the contact part of it is ``sum_{i in S} J_i(q)^T f_i``
with ``J_i`` the Jacobian of foot i's sole site: translational (3 rows, ``f_i`` a force) for point
feet, translational and rotational (6 rows, a wrench) for flat feet of several contact geoms. The
per-foot forces are the least-squares solution over all dofs, so damping or other non-contact
parts of ``eps`` are left in the misfit rather than forced onto the feet. The vertical component
of ``f_i`` is compared with the dataset's normal force. The same map applied to the *true*
residual (``qfrc_passive + qfrc_constraint + qfrc_external``) gives the floor this mapping puts
under any model's error (reported as the oracle).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from stride_jax.dynamics import linalg
from stride_jax.sim.model import SimModel


def foot_jacobians(sm: SimModel, q: np.ndarray) -> np.ndarray:
    """``[N, nfeet, k, nv]`` sole-site Jacobians at configurations ``q [N, nq]``; ``k`` is 3 for
    point feet (one contact geom) and 6 for flat feet (several)."""
    m = sm.mj
    d = mujoco.MjData(m)
    k = 6 if (sm.foot_geoms >= 0).sum(1).max(initial=0) > 1 else 3
    out = np.zeros((len(q), sm.nfeet, k, m.nv))
    jacp, jacr = np.zeros((3, m.nv)), np.zeros((3, m.nv))
    for n, qn in enumerate(np.asarray(q, np.float64)):
        d.qpos[:] = qn
        mujoco.mj_kinematics(m, d)
        mujoco.mj_comPos(m, d)
        for i, site in enumerate(sm.foot_sites):
            mujoco.mj_jacSite(m, d, jacp, jacr, int(site))
            out[n, i, :3] = jacp
            if k == 6:
                out[n, i, 3:] = jacr
    return out


@jax.jit
def foot_forces(jac: jax.Array, stance: jax.Array, eps: jax.Array) -> jax.Array:
    """``[nfeet, k]``: forces (wrenches) of the stance feet that best produce ``eps [nv]`` through
    ``J^T`` (least squares with a tiny ridge); zero for feet not in stance. One example."""
    nfeet, k, nv = jac.shape
    A = (jac * stance[:, None, None]).reshape(nfeet * k, nv).T  # [nv, nfeet k]
    AtA = A.T @ A
    ridge = 1e-9 * jnp.trace(AtA) + 1e-12
    # spd_solve, not LAPACK's LU: vmapped over examples on a small CPU, jaxlib's batched LAPACK
    # calls can deadlock (stride_jax.dynamics.linalg)
    f = linalg.spd_solve(AtA + ridge * jnp.eye(nfeet * k), A.T @ eps)
    return f.reshape(nfeet, k) * stance[:, None]


def normal_force_errors(jac, stance, eps, true_normal) -> np.ndarray:
    """``[N, nfeet]`` absolute error of the vertical force (N), NaN where the foot is in swing.
    ``jac [N, nfeet, k, nv]``, ``stance``/``true_normal [N, nfeet]``, ``eps [N, nv]``."""
    f = jax.vmap(foot_forces)(jnp.asarray(jac, jnp.float32), jnp.asarray(stance, jnp.float32),
                              jnp.asarray(eps, jnp.float32))
    err = np.abs(np.asarray(f[..., 2]) - true_normal)
    return np.where(stance, err, np.nan)


def residual_share(prior_acc: np.ndarray, residual_acc: np.ndarray, qdd_scale: np.ndarray
                   ) -> np.ndarray:
    """``[N]``: the residual's share ``|M^-1 eps| / (|f_LNN| + |M^-1 eps|)`` of the predicted
    acceleration ``qdd = f_LNN + M^-1 eps``, in [0, 1], with accelerations normalised per dof by
    ``qdd_scale`` (so that a share is not decided by the units of one dof)."""
    res = np.linalg.norm(residual_acc / qdd_scale, axis=-1)
    prior = np.linalg.norm(prior_acc / qdd_scale, axis=-1)
    return res / np.maximum(res + prior, 1e-12)
