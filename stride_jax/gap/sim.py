"""Stepping a :class:`~stride_jax.gap.effects.Plan` on the CPU: one-step replays of logged states,
open-loop rollouts from logged states, and closed-loop runs that produce "real" trajectories.

Why CPU MuJoCo and not MJX: the "real" robot of the issue is MJX with effects; CPU MuJoCo runs the
same physics (same model, same solver settings, ``stride_jax.sim.rollout_cpu`` checks the two
agree) about 30x faster on a CPU, and ``mujoco.rollout`` steps many initial states in one threaded
call, which is what one-step replays and parameter fits need (thousands of states per evaluation).
Every function batches over states with ``mujoco.rollout``; Python loops run over control steps
only where the controller-side effects need the simulated state (dead band, drag).
"""

from __future__ import annotations

import copy
import dataclasses
import os
import threading
from typing import Callable

import mujoco
import mujoco.rollout
import numpy as np

from stride_jax.gap import effects, memo
from stride_jax.gap.effects import Plan
from stride_jax.sim.model import SimModel

_STATE = mujoco.mjtState.mjSTATE_FULLPHYSICS
_CONTROL = mujoco.mjtState.mjSTATE_CTRL | mujoco.mjtState.mjSTATE_QFRC_APPLIED


# MuJoCo resets a world whose state turns NaN, Inf or huge (mjWARN_BADQACC and kin) to its
# initial pose and goes on, printing a warning once per MjData. A reset replay looks like a finite
# prediction, so :func:`step` starts every world at time _T0 and reads a reset off the clock; the
# warnings are counted here instead of printed (:func:`unstable`), since a fit may probe thousands
# of unstable parameter values.
_T0 = 1.0
_COUNT = {"warnings": 0, "diverged": 0}
_LOCK = threading.Lock()


def _count_warning(msg: str) -> None:
    with _LOCK:
        _COUNT["warnings"] += 1


def n_diverged(q: np.ndarray, qd: np.ndarray) -> int:
    """Worlds of a step's result that diverged (returned as NaN by :func:`step`)."""
    return int((~(np.isfinite(q).all(-1) & np.isfinite(qd).all(-1))).sum())


def _count_diverged(n: int) -> None:
    if n:
        with _LOCK:
            _COUNT["diverged"] += int(n)


def unstable() -> dict[str, int]:
    """Running totals since import: MuJoCo's instability warnings (``warnings``) and diverged
    worlds (``diverged``, reset by MuJoCo or non-finite) over all :func:`step` calls. Read it
    before and after a computation to count what that computation met."""
    return dict(_COUNT)


def nthread() -> int:
    return int(os.environ.get("STRIDE_GAP_THREADS", os.cpu_count() or 1))


def for_replay(sm: SimModel) -> SimModel:
    """``sm`` as the gap tool replays it: the same dynamics, with MuJoCo's sparse constraint
    Jacobian where the model has a floating base.

    ``opt.jacobian`` is numerics only (the results agree to rounding, ~1e-13 in the velocities):
    MuJoCo's ``auto`` picks the dense form below 60 dofs, but a floating base with legs gives a
    Jacobian that is mostly zeros, and the shipped Go1 (18 dofs, elliptic cones) steps its logged
    windows in 52 us against 70 us dense on one core (``experiments/probes/replay_jacobian.py``);
    the G1 and a pendulum step alike either way. The model is copied: ``sm`` is left as it is."""
    m = sm.mj
    free = bool(np.any(m.jnt_type == mujoco.mjtJoint.mjJNT_FREE))
    if not free or m.opt.jacobian == mujoco.mjtJacobian.mjJAC_SPARSE:
        return sm
    mj = copy.copy(m)
    mj.opt.jacobian = mujoco.mjtJacobian.mjJAC_SPARSE
    return dataclasses.replace(sm, mj=mj)


def _states(m: mujoco.MjModel, q: np.ndarray, qd: np.ndarray) -> np.ndarray:
    """Full-physics states ``[B, nstate]`` at configurations ``q [B, nq]``, velocities ``qd [B, nv]``."""
    d = mujoco.MjData(m)
    mujoco.mj_resetData(m, d)
    tmpl = np.zeros(mujoco.mj_stateSize(m, _STATE))
    mujoco.mj_getState(m, d, tmpl, _STATE)
    s = np.repeat(tmpl[None], len(q), 0)
    s[:, 1:1 + m.nq] = q
    s[:, 1 + m.nq:1 + m.nq + m.nv] = qd
    return s


def _drag(sm: SimModel, plan: Plan, qd: np.ndarray) -> np.ndarray:
    """``[B, nv]`` the hidden quadratic joint drag at velocities ``qd [B, nv]`` (zero if unused)."""
    f = np.zeros_like(qd)
    if plan.drag:
        v = qd[:, sm.act_dof]
        f[:, sm.act_dof] = -plan.drag * v * np.abs(v)
    return f


def step(sm: SimModel, plan: Plan, q: np.ndarray, qd: np.ndarray, u: np.ndarray
         ) -> tuple[np.ndarray, np.ndarray]:
    """One control period from ``B`` states under per-simulation-step controls ``u [B, n_sub, nu]``.

    Returns the next ``(q [B, nq], qd [B, nv])``, NaN where the simulation diverged (MuJoCo's
    reset of an unstable world is detected and undone; its warning is counted, not printed).
    """
    m, n_sub = plan.mj, sm.n_substeps
    if u.shape != (len(q), n_sub, m.nu):
        raise ValueError(f"controls have shape {list(u.shape)}, expected [{len(q)}, {n_sub}, {m.nu}]")
    control = np.concatenate([u, np.repeat(_drag(sm, plan, qd)[:, None], n_sub, 1)], axis=2)
    spec = _CONTROL
    if plan.wrench is not None:  # a constant wrench on the base: xfrc_applied of every body
        x = np.zeros((m.nbody, 6))
        x[sm.base_body] = plan.wrench
        control = np.concatenate([control, np.broadcast_to(x.ravel(), control.shape[:2] + (x.size,))], axis=2)
        spec = _CONTROL | mujoco.mjtState.mjSTATE_XFRC_APPLIED
    nt = max(1, min(nthread(), len(q)))
    datas = [mujoco.MjData(m) for _ in range(nt)]
    s0 = _states(m, q, qd)
    s0[:, 0] = _T0
    previous = mujoco.get_mju_user_warning()
    mujoco.set_mju_user_warning(_count_warning)
    try:
        states, _ = mujoco.rollout.rollout(m, datas, s0, control, control_spec=spec, persistent_pool=True)
    finally:
        mujoco.set_mju_user_warning(previous)
    last = states[:, -1]
    q1, qd1 = last[:, 1:1 + m.nq].copy(), last[:, 1 + m.nq:1 + m.nq + m.nv].copy()
    bad = (np.abs(last[:, 0] - (_T0 + n_sub * m.opt.timestep)) > 0.5 * m.opt.timestep)
    bad |= ~(np.isfinite(q1).all(1) & np.isfinite(qd1).all(1))
    if bad.any():
        with _LOCK:
            _COUNT["diverged"] += int(bad.sum())
        q1[bad], qd1[bad] = np.nan, np.nan
    return q1, qd1


def _act_q(sm: SimModel, q: np.ndarray) -> np.ndarray:
    return q[..., sm.mj.jnt_qposadr[sm.mj.actuator_trnid[:, 0]]]


def true_q(plan: Plan, q: np.ndarray) -> np.ndarray:
    """Logged (encoder) positions ``q [..., nq]`` as the simulator's configuration: less the plan's
    encoder offsets."""
    return q if plan.q_offset is None else q - plan.q_offset


def logged_q(plan: Plan, q: np.ndarray) -> np.ndarray:
    """The simulator's configuration ``q [..., nq]`` as the encoders log it."""
    return q if plan.q_offset is None else q + plan.q_offset


def k_step(sm: SimModel, plan: Plan, q: np.ndarray, qd: np.ndarray, cmd: np.ndarray,
           start: np.ndarray, first: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Replays logged states ``k`` control periods ahead under the logged commands (multiple
    shooting: ``k = 1`` is the one-step replay).

    ``q [N, nq]``, ``qd [N, nv]``, ``cmd [N, nu]``: the concatenated samples of all trajectories;
    ``start [M]`` the samples to start from (``start + k`` inside their trajectory) and ``first [M]``
    the first sample of each one's trajectory (the command before it is held from there).
    Returns the predicted state after ``k`` periods, ``(q [M, nq], qd [M, nv])``: read-only
    where they come from :mod:`stride_jax.gap.memo` (a replay made before returns its result).
    """
    key = None
    if memo.enabled():
        key = memo.windows_key(sm, q, qd, cmd, start, first, k) + memo.plan_key(plan)
        if (hit := memo.get(key)) is not None:
            _count_diverged(hit[2])
            return hit[:2]
    n_sub, servo = sm.n_substeps, sm.robot.kp is not None
    x, v = true_q(plan, q[start]), qd[start]
    diverged = 0  # what step() counted: the worlds it returned as NaN, per period
    for h in range(k):
        i = (start + h)[:, None] * n_sub + np.arange(n_sub)[None, :] - plan.delay
        src = np.maximum(np.floor_divide(i, n_sub), first[:, None])
        u = effects.dead_band(cmd[src], _act_q(sm, logged_q(plan, x))[:, None], plan.deadzone, servo)
        x, v = step(sm, plan, x, v, u)
        diverged += n_diverged(x, v)
    return (logged_q(plan, x), v) if key is None else memo.put(key, logged_q(plan, x), v, diverged)


def one_step(sm: SimModel, plan: Plan, q: np.ndarray, qd: np.ndarray, cmd: np.ndarray,
             bounds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`k_step` with ``k = 1`` from every sample but each trajectory's last (``bounds
    [n_traj + 1]`` are the trajectory starts)."""
    start = np.concatenate([np.arange(a, b - 1) for a, b in zip(bounds[:-1], bounds[1:])])
    first = np.concatenate([np.full(b - a - 1, a) for a, b in zip(bounds[:-1], bounds[1:])])
    return k_step(sm, plan, q, qd, cmd, start, first, 1)


def rollout(sm: SimModel, plan: Plan, q0: np.ndarray, qd0: np.ndarray, cmd: np.ndarray,
            start: np.ndarray, horizon: int) -> tuple[np.ndarray, np.ndarray]:
    """Open-loop rollouts under the logged commands of one trajectory.

    ``q0 [W, nq]``, ``qd0 [W, nv]`` initial states at control steps ``start [W]``; ``cmd [T, nu]`` the
    trajectory's commands (``start + horizon <= T``). Returns ``q [W, horizon, nq]``,
    ``qd [W, horizon, nv]``: the states after 1..horizon control periods.
    """
    q, qd = true_q(plan, np.asarray(q0, np.float64)), np.asarray(qd0, np.float64)
    qs, qds = [], []
    for h in range(horizon):
        u = np.stack([effects.substep_commands(cmd, np.array([s + h]), plan.delay, sm.n_substeps)[0]
                      for s in start])
        u = effects.dead_band(u, _act_q(sm, logged_q(plan, q))[:, None], plan.deadzone, sm.robot.kp is not None)
        q, qd = step(sm, plan, q, qd, u)
        qs.append(logged_q(plan, q))
        qds.append(qd)
    return np.stack(qs, 1), np.stack(qds, 1)


def actuator_force(sm: SimModel, m: mujoco.MjModel, u: np.ndarray, q: np.ndarray, qd: np.ndarray
                   ) -> np.ndarray:
    """``[B, nu]`` force of MuJoCo's affine actuators (motors, position servos) under ``u [B, nu]``."""
    dof = sm.act_dof
    f = (m.actuator_gainprm[:, 0] * u + m.actuator_biasprm[:, 0] + m.actuator_biasprm[:, 1] * _act_q(sm, q)
         + m.actuator_biasprm[:, 2] * qd[:, dof])
    lim = m.actuator_forcelimited.astype(bool)
    return np.where(lim, np.clip(f, m.actuator_forcerange[:, 0], m.actuator_forcerange[:, 1]), f)


def closed_loop(sm: SimModel, plan: Plan, q0: np.ndarray, qd0: np.ndarray,
                policy: Callable[[int, np.ndarray, np.ndarray], np.ndarray], n_steps: int,
                fallen: Callable[[np.ndarray], np.ndarray] | None = None) -> dict[str, np.ndarray]:
    """Runs ``B`` worlds under ``policy(step, q [B, nq], qd [B, nv]) -> commands [B, nu]``.

    The commands pass through the plan's delay and dead band before they reach the actuators.
    Returns ``t [T]``, ``q [B, T, nq]``, ``qd [B, T, nv]``, ``cmd [B, T, nu]`` (as commanded),
    ``tau [B, T, nu]`` (actuator force at the sample), ``qdd [B, T, nv]`` (mean acceleration over
    the following period) and ``valid [B, T]`` (not fallen, finite, up to and including the step).
    """
    q, qd = np.asarray(q0, np.float64).copy(), np.asarray(qd0, np.float64).copy()
    B, n_sub = len(q), sm.n_substeps
    hist = np.zeros((B, n_steps, sm.mj.nu))
    out = {k: [] for k in ("q", "qd", "tau", "valid")}
    alive = np.ones(B, bool)
    servo = sm.robot.kp is not None
    for t in range(n_steps):
        ok = np.isfinite(q).all(1) & np.isfinite(qd).all(1)
        if fallen is not None:
            ok &= ~fallen(np.where(np.isfinite(q), q, 0.0))
        alive &= ok
        q, qd = np.where(alive[:, None], q, q0), np.where(alive[:, None], qd, qd0)  # park dead worlds
        hist[:, t] = np.asarray(policy(t, logged_q(plan, q), qd), np.float64)  # the robot sees its encoders
        u = np.stack([effects.substep_commands(hist[b, :t + 1], np.array([t]), plan.delay, n_sub)[0]
                      for b in range(B)])
        u = effects.dead_band(u, _act_q(sm, logged_q(plan, q))[:, None], plan.deadzone, servo)
        out["q"].append(logged_q(plan, q))
        out["qd"].append(qd)
        out["tau"].append(actuator_force(sm, plan.mj, u[:, 0], q, qd))
        out["valid"].append(alive.copy())
        q, qd = step(sm, plan, q, qd, u)
    res = {k: np.stack(v, 1) for k, v in out.items()}
    res["cmd"] = hist
    qd_all = np.concatenate([res["qd"], qd[:, None]], 1)
    res["qdd"] = np.diff(qd_all, axis=1) / sm.robot.ctrl_dt
    res["t"] = sm.robot.ctrl_dt * np.arange(n_steps)
    return res
