"""Where a replay's MuJoCo time goes: MuJoCo's own timers on a robot's gap-diagnosis model.

    python experiments/probes/mujoco_step_timers.py [--robot go1] [--steps 3000]

Steps the shipped and the MJX-training form of the robot (``stride_jax.gap.nominal.load``) from its
``home`` keyframe under position targets swinging around it (2 Hz), prints microseconds per step and
each timer above 2% of the step; then the same with the solver's warm start zeroed every control
period, as each of the gap replay's ``mujoco.rollout`` calls (one per control period) starts it.
"""

from __future__ import annotations

import argparse
import time

import mujoco
import numpy as np


def run(m: mujoco.MjModel, steps: int, cold_every: int = 0) -> tuple[mujoco.MjData, float, float]:
    d = mujoco.MjData(m)
    k = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_KEY, "home")
    if k >= 0:
        mujoco.mj_resetDataKeyframe(m, d, k)
    home = d.qpos[-m.nu:].copy()
    its, t0 = 0, time.perf_counter()
    for i in range(steps):
        if cold_every and i % cold_every == 0:
            d.qacc_warmstart[:] = 0
        d.ctrl[:] = home + 0.3 * np.sin(2 * np.pi * 2 * i * m.opt.timestep + np.arange(m.nu))
        mujoco.mj_step(m, d)
        its += int(d.solver_niter[0])
    return d, (time.perf_counter() - t0) / steps, its / steps


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robot", default="go1")
    ap.add_argument("--steps", type=int, default=3000)
    a = ap.parse_args()
    from stride_jax.gap import nominal

    for form in ("shipped", "training"):
        sm = nominal.load(a.robot, form)
        m = sm.mj
        d, per, its = run(m, a.steps)
        tot = d.timer[mujoco.mjtTimer.mjTIMER_STEP].duration
        print(f"{form}: time step {m.opt.timestep * 1e3:g} ms, cone {'elliptic' if m.opt.cone else 'pyramidal'}, "
              f"{per * 1e6:.1f} us per step, {its:.2f} solver iterations per step")
        for name in dir(mujoco.mjtTimer):
            if name.startswith("mjTIMER_") and name != "mjTIMER_STEP":
                share = d.timer[getattr(mujoco.mjtTimer, name)].duration / tot
                if share > 0.02:
                    print(f"   {name:28s} {share:6.1%}")
        n_sub = sm.n_substeps
        _, per_c, its_c = run(m, a.steps, cold_every=n_sub)
        print(f"   warm start zeroed every control period ({n_sub} steps): {per_c * 1e6:.1f} us per step, "
              f"{its_c:.2f} solver iterations per step")


if __name__ == "__main__":
    main()
