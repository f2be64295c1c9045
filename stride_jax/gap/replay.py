"""Many hypotheses replayed at once: one threaded ``mujoco.rollout`` call per control period over
every (plan, replay window) pair.

:func:`stride_jax.gap.sim.k_step` replays one :class:`~stride_jax.gap.effects.Plan` at a time;
a screen over a hundred hypotheses, or a grid over one parameter, would pay the call's set-up and
Python's per-period work a hundred times, and hand MuJoCo's thread pool small batches. Here each
world of the batch gets its own model (``mujoco.rollout`` takes one ``MjModel`` per world), its own
controls (delay, dead band, drag, base wrench) and its own start state (encoder offsets), and the
batch is cut into chunks of at most ``chunk`` worlds to bound memory (the rollout returns every
substep's state). Each world's result is the one :func:`~stride_jax.gap.sim.k_step` gives for it
alone (tested bit for bit).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import mujoco
import mujoco.rollout
import numpy as np

from stride_jax.gap import effects, memo, sim
from stride_jax.gap.effects import Plan
from stride_jax.sim.model import SimModel

if TYPE_CHECKING:
    from stride_jax.gap import fit

CHUNK = 40_000  # worlds per rollout call: ~40 MB of states for the Go1


def _controls(sm: SimModel, plan: Plan, x: np.ndarray, v: np.ndarray, cmd: np.ndarray,
              start: np.ndarray, first: np.ndarray, h: int, wrench: bool) -> np.ndarray:
    """``[M, n_sub, ncontrol]`` controls of one plan for period ``h`` of its windows."""
    n_sub, servo = sm.n_substeps, sm.robot.kp is not None
    i = (start + h)[:, None] * n_sub + np.arange(n_sub)[None, :] - plan.delay
    src = np.maximum(np.floor_divide(i, n_sub), first[:, None])
    u = effects.dead_band(cmd[src], sim._act_q(sm, sim.logged_q(plan, x))[:, None], plan.deadzone, servo)
    parts = [u, np.repeat(sim._drag(sm, plan, v)[:, None], n_sub, 1)]
    if wrench:
        xf = np.zeros((sm.mj.nbody, 6))
        if plan.wrench is not None:
            xf[sm.base_body] = plan.wrench
        parts.append(np.broadcast_to(xf.ravel(), u.shape[:2] + (xf.size,)))
    return np.concatenate(parts, axis=2)


def _rollout(sm: SimModel, models: list, s0: np.ndarray, control: np.ndarray, spec: int
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One period of every world: ``(q, qd, diverged)``, NaN and True where a world diverged."""
    m0, n_sub = sm.mj, sm.n_substeps
    nt = max(1, min(sim.nthread(), len(s0)))
    datas = [mujoco.MjData(m0) for _ in range(nt)]
    s0 = s0.copy()
    s0[:, 0] = sim._T0
    previous = mujoco.get_mju_user_warning()
    mujoco.set_mju_user_warning(sim._count_warning)
    try:
        states, _ = mujoco.rollout.rollout(models, datas, s0, control, control_spec=spec, persistent_pool=True)
    finally:
        mujoco.set_mju_user_warning(previous)
    last = states[:, -1]
    q1, qd1 = last[:, 1:1 + m0.nq].copy(), last[:, 1 + m0.nq:1 + m0.nq + m0.nv].copy()
    dt = m0.opt.timestep
    bad = np.abs(last[:, 0] - (sim._T0 + n_sub * np.array([m.opt.timestep for m in models]))) > 0.5 * dt
    bad |= ~(np.isfinite(q1).all(1) & np.isfinite(qd1).all(1))
    if bad.any():
        with sim._LOCK:
            sim._COUNT["diverged"] += int(bad.sum())
        q1[bad], qd1[bad] = np.nan, np.nan
    return q1, qd1, bad


def k_step_many(sm: SimModel, plans: list[Plan], q: np.ndarray, qd: np.ndarray, cmd: np.ndarray,
                start: np.ndarray, first: np.ndarray, k: int, chunk: int = CHUNK
                ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`stride_jax.gap.sim.k_step` for every plan of ``plans`` at once.

    Returns the logged-frame state after ``k`` periods, ``q [P, M, nq]``, ``qd [P, M, nv]`` (NaN
    where a replay diverged). Plans replayed on these windows before (:mod:`stride_jax.gap.memo`)
    are not replayed again."""
    if not memo.enabled():
        return _k_step_many(sm, plans, q, qd, cmd, start, first, k, chunk)[:2]
    P, M = len(plans), len(start)
    qo, vo = np.empty((P, M, sm.mj.nq)), np.empty((P, M, sm.mj.nv))
    wk = memo.windows_key(sm, q, qd, cmd, start, first, k)
    keys, todo = [wk + memo.plan_key(p) for p in plans], {}
    for i, key in enumerate(keys):
        if (hit := memo.get(key)) is not None:
            qo[i], vo[i] = hit[:2]
            sim._count_diverged(hit[2])
        elif key in todo:  # the same plan twice in one call: replayed once
            todo[key].append(i)
        else:
            todo[key] = [i]
    if todo:
        qn, vn, nd = _k_step_many(sm, [plans[ix[0]] for ix in todo.values()], q, qd, cmd, start, first, k, chunk)
        for j, (key, ix) in enumerate(todo.items()):
            memo.put(key, qn[j], vn[j], nd[j])
            qo[ix], vo[ix] = qn[j], vn[j]
    return qo, vo


def _k_step_many(sm: SimModel, plans: list[Plan], q: np.ndarray, qd: np.ndarray, cmd: np.ndarray,
                 start: np.ndarray, first: np.ndarray, k: int, chunk: int
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The replays themselves; also returns ``[P]`` how many worlds of each plan diverged (summed
    over the periods, as :func:`_rollout` counts them)."""
    P, M = len(plans), len(start)
    wrench = any(p.wrench is not None for p in plans)
    spec = sim._CONTROL | (mujoco.mjtState.mjSTATE_XFRC_APPLIED if wrench else 0)
    per = max(1, chunk // max(M, 1))  # plans per call
    qo, vo = np.empty((P, M, sm.mj.nq)), np.empty((P, M, sm.mj.nv))
    diverged = np.zeros(P, np.int64)
    for c0 in range(0, P, per):
        group = plans[c0:c0 + per]
        x = np.concatenate([sim.true_q(p, q[start]) for p in group])
        v = np.tile(qd[start], (len(group), 1))
        models = [p.mj for p in group for _ in range(M)]
        for h in range(k):
            control = np.concatenate([_controls(sm, p, x[j * M:(j + 1) * M], v[j * M:(j + 1) * M], cmd, start,
                                                first, h, wrench) for j, p in enumerate(group)])
            s0 = sim._states(sm.mj, x, v)
            x, v, bad = _rollout(sm, models, s0, control, spec)
            diverged[c0:c0 + len(group)] += bad.reshape(len(group), M).sum(1)
        for j, p in enumerate(group):
            qo[c0 + j] = sim.logged_q(p, x[j * M:(j + 1) * M])
            vo[c0 + j] = v[j * M:(j + 1) * M]
    return qo, vo, diverged


def residuals(sm: SimModel, plans: list[Plan], data: fit.Data, scale: np.ndarray,
              rows: np.ndarray | None = None) -> np.ndarray:
    """``[P, M', nv]`` :func:`stride_jax.gap.fit.residual` of each plan on the replays ``rows`` of
    ``data`` (all for None)."""
    rows = np.arange(len(data.start)) if rows is None else np.asarray(rows)
    _, qd = k_step_many(sm, plans, data.q, data.qd, data.cmd, data.start[rows], data.first[rows], data.k)
    r = (qd - data.target[rows]) / (data.k * sm.robot.ctrl_dt * scale)
    return np.where(np.isfinite(r), np.clip(r, -1e3, 1e3), 1e3)
