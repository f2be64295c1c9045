"""Dense or sparse constraint Jacobian for the gap tool's replays: time per MuJoCo step, and how far apart.

    python experiments/probes/replay_jacobian.py [--robots go1,g1,pendulum] [--windows 400]

For each robot's shipped nominal model (``stride_jax.gap.nominal.load``) steps, on one core, the
one-period replay windows of logs that the Go1 explorer writes on it (``stride_jax.gap.real.generate``,
no effect planted; other robots: position targets swinging around the home pose), once with
``opt.jacobian`` dense and once sparse, three times each in turn, and prints microseconds per step
and the largest difference of the replayed velocities. ``stride_jax.gap.sim.for_replay`` takes the
sparse form for floating-base models.
"""

from __future__ import annotations

import argparse
import copy
import time

import mujoco
import numpy as np


def windows(m: mujoco.MjModel, starts: list[tuple[np.ndarray, np.ndarray, np.ndarray]], n_sub: int
            ) -> tuple[float, np.ndarray]:
    d = mujoco.MjData(m)
    out, t0 = [], time.perf_counter()
    for q, v, u in starts:
        d.qpos[:], d.qvel[:], d.ctrl[:] = q, v, u
        d.qacc_warmstart[:] = 0  # each replay call starts cold
        for _ in range(n_sub):
            mujoco.mj_step(m, d)
        out.append(d.qvel.copy())
    return (time.perf_counter() - t0) / (len(starts) * n_sub) * 1e6, np.array(out)


def swing_starts(m: mujoco.MjModel, n: int, n_sub: int) -> list:
    d = mujoco.MjData(m)
    k = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_KEY, "home") if m.nkey else -1
    if k >= 0:
        mujoco.mj_resetDataKeyframe(m, d, k)
    home = d.qpos[-m.nu:].copy() if m.nu else np.zeros(0)
    out = []
    for i in range(n * n_sub):
        u = home + 0.3 * np.sin(2 * np.pi * 2 * i * m.opt.timestep + np.arange(m.nu))
        if i % n_sub == 0:
            out.append((d.qpos.copy(), d.qvel.copy(), u))
        d.ctrl[:] = u
        mujoco.mj_step(m, d)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", default="go1,g1,pendulum")
    ap.add_argument("--windows", type=int, default=400)
    a = ap.parse_args()
    from stride_jax.gap import nominal, real

    for robot in a.robots.split(","):
        sm = nominal.load(robot, "shipped")
        n_sub = sm.n_substeps
        if robot == "go1":
            _, lg = real.generate(sm, {}, 2, a.windows // 2 + 1, 3)
            starts = [(t.q[i], t.qd[i], t.cmd[i]) for t in lg for i in range(len(t.t) - 1)][:a.windows]
            what = "logged windows"
        else:
            starts = swing_starts(sm.mj, a.windows, n_sub)
            what = "swinging around home"
        times: dict[int, list[float]] = {0: [], 1: []}
        outs = {}
        for _ in range(3):
            for jac in (mujoco.mjtJacobian.mjJAC_DENSE, mujoco.mjtJacobian.mjJAC_SPARSE):
                m = copy.copy(sm.mj)
                m.opt.jacobian = jac
                t, outs[int(jac)] = windows(m, starts, n_sub)
                times[int(jac)].append(t)
        diff = float(np.abs(outs[0] - outs[1]).max())
        print(f"{robot} ({what}, {len(starts)} x {n_sub} steps, nv {sm.mj.nv}): dense {min(times[0]):.1f} us, "
              f"sparse {min(times[1]):.1f} us per step (best of 3); max |velocity difference| {diff:.1e}")


if __name__ == "__main__":
    main()
