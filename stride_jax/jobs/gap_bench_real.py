"""The "real" robot of the independent gap benchmark, written apart from the diagnosis.

The diagnosis fits effects with its own code (:mod:`stride_jax.gap.effects`, ``sim``, ``real``);
this module imports none of it (tested), so that the benchmark's "real" logs are not made by the
code they test:

* **its own model**: the robot's MJCF loaded and compiled here (for the Go1: Menagerie's
  ``scene.xml`` as shipped), with **simulator settings drawn per case** (:func:`draw_settings`)
  that differ from the nominal model: time step, integrator, friction cone, impratio, contact
  solref (time constant, damping ratio), solimp (``1 - d`` of d0 and dmax with *separate*
  factors, which the calibration cannot represent exactly, and the width), margin, and the
  collision set (feet only);
* **its own planting** of the effects (:func:`plant`: edits of the ``MjModel`` fields, a command
  delay in seconds at the real time step, a servo dead band, a per-step quadratic drag, and the
  joint and actuator effects on some joints only, by name);
* **its own controller** (a numpy trot / pronk / bound / pace position reference for the Go1,
  random torque sines for the pendulum) stepped with ``mujoco.mj_step``;
* **its own sensor model** (:class:`Go1Sensors`: a real Go1's encoder resolution, joint-velocity
  noise, estimator drift and noise, gyro noise, velocity glitches), on top of clean logs.

:func:`generate` makes one case's logs; :mod:`stride_jax.jobs.gap_bench_independent` runs the
benchmark and :mod:`stride_jax.jobs.gap_bench_score` scores it.
"""

from __future__ import annotations

import copy
import dataclasses
from typing import Any

import mujoco
import numpy as np

from stride_jax.gap import logs
from stride_jax.sim import model as sim_model

def robot_spec(name: str) -> mujoco.MjSpec:
    """The robot's MJCF as shipped (Menagerie's Go1 ``scene.xml``; the pendulum's asset), parsed here."""
    from stride_jax import robots

    if name not in ("go1", "pendulum"):
        raise ValueError(f"the independent benchmark knows robots 'go1' and 'pendulum', not {name!r}")
    spec = robots.get(name).load_spec()
    sim_model.strip_visual_meshes(spec)
    return spec


def draw_settings(m: mujoco.MjModel, rng: np.random.Generator, ctrl_dt: float) -> dict[str, Any]:
    """Random simulator settings of the "real" robot (at least one differs from the model's): each
    of time step, integrator, cone, contact parameters (and, for a model with contacts, the
    feet-only collision set) changes with probability 1/2."""
    contacts = bool(((m.geom_contype != 0) | (m.geom_conaffinity != 0)).any())
    dims = ["timestep", "integrator"] + (["cone", "contact", "collision"] if contacts else [])
    while True:
        pick = [d for d in dims if rng.random() < 0.5]
        if pick:
            break
    s: dict[str, Any] = {}
    if "timestep" in pick:
        opts = [dt for dt in (0.001, 0.002, 0.0025, 0.004, 0.005, 0.01)
                if abs(dt - m.opt.timestep) > 1e-9 and abs(ctrl_dt / dt - round(ctrl_dt / dt)) < 1e-9]
        s["timestep"] = float(rng.choice(opts))
    if "integrator" in pick:
        opts = [i for i in ("implicitfast", "rk4", "euler_nodamp", "euler") if i != _integrator_name(m)]
        s["integrator"] = str(rng.choice(opts))
    if "cone" in pick:
        s["cone"] = "pyramidal" if m.opt.cone == mujoco.mjtCone.mjCONE_ELLIPTIC else "elliptic"
    if "contact" in pick:
        s["solref_timeconst_factor"] = float(np.exp(rng.uniform(np.log(0.6), np.log(1.8))))
        s["solref_dampratio_factor"] = float(np.exp(rng.uniform(np.log(0.6), np.log(1.6))))
        s["solimp_d0_factor"] = float(np.exp(rng.uniform(np.log(0.5), np.log(2.0))))
        s["solimp_dmax_factor"] = float(np.exp(rng.uniform(np.log(0.5), np.log(2.0))))
        s["solimp_width_factor"] = float(np.exp(rng.uniform(np.log(0.5), np.log(2.0))))
        s["margin_added"] = float(rng.uniform(0.0, 0.003))
        s["impratio"] = float(np.exp(rng.uniform(np.log(1.0), np.log(300.0))))
    if "collision" in pick:
        s["feet_only"] = True
    return s


def _integrator_name(m: mujoco.MjModel) -> str:
    i = int(m.opt.integrator)
    if i == int(mujoco.mjtIntegrator.mjINT_EULER):
        return "euler_nodamp" if m.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_EULERDAMP) else "euler"
    return {int(mujoco.mjtIntegrator.mjINT_RK4): "rk4", int(mujoco.mjtIntegrator.mjINT_IMPLICIT): "implicit",
            int(mujoco.mjtIntegrator.mjINT_IMPLICITFAST): "implicitfast"}[i]


def set_simulator(m: mujoco.MjModel, s: dict[str, Any], feet: list[str]) -> None:
    """Puts drawn settings ``s`` on ``m`` in place."""
    if "timestep" in s:
        m.opt.timestep = s["timestep"]
    if "integrator" in s:
        flag = int(mujoco.mjtDisableBit.mjDSBL_EULERDAMP)
        name = s["integrator"]
        m.opt.integrator = {"implicitfast": mujoco.mjtIntegrator.mjINT_IMPLICITFAST, "rk4": mujoco.mjtIntegrator.mjINT_RK4,
                            "euler": mujoco.mjtIntegrator.mjINT_EULER,
                            "euler_nodamp": mujoco.mjtIntegrator.mjINT_EULER}[name]
        m.opt.disableflags = (m.opt.disableflags | flag) if name == "euler_nodamp" else (m.opt.disableflags & ~flag)
    if "cone" in s:
        m.opt.cone = mujoco.mjtCone.mjCONE_PYRAMIDAL if s["cone"] == "pyramidal" else mujoco.mjtCone.mjCONE_ELLIPTIC
    if "solref_timeconst_factor" in s:
        m.geom_solref[:, 0] *= s["solref_timeconst_factor"]
        m.geom_solref[:, 1] *= s["solref_dampratio_factor"]
        m.geom_solimp[:, 0] = np.clip(1 - (1 - m.geom_solimp[:, 0]) * s["solimp_d0_factor"], 1e-3, 0.999)
        m.geom_solimp[:, 1] = np.clip(1 - (1 - m.geom_solimp[:, 1]) * s["solimp_dmax_factor"], 1e-3, 0.999)
        m.geom_solimp[:, 2] *= s["solimp_width_factor"]
        m.geom_margin[:] += s["margin_added"]
        m.opt.impratio = s["impratio"]
    if s.get("feet_only"):
        ids = {mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, f) for f in feet}
        for g in range(m.ngeom):
            if m.geom_bodyid[g] == 0:
                m.geom_contype[g], m.geom_conaffinity[g] = 1, 0
            elif g in ids:
                m.geom_contype[g], m.geom_conaffinity[g] = 0, 1
            else:
                m.geom_contype[g], m.geom_conaffinity[g] = 0, 0


@dataclasses.dataclass
class Controller:
    """How the commands reach the "real" actuators: a delay (sim steps), a servo dead band (rad),
    a quadratic joint drag (N m s^2/rad^2, applied at every simulation step)."""

    delay_steps: int = 0
    deadband: float = 0.0
    drag: float = 0.0


_ON_JOINTS = ("damping", "frictionloss", "armature", "torque_scale", "torque_limit", "kp_scale")


def plant(m: mujoco.MjModel, planted: dict[str, Any], joints: tuple[str, ...], base_body: str) -> Controller:
    """Puts the planted effects on the "real" model ``m`` (in place) and returns the controller side.

    Written here, apart from the diagnosis's effect code: added joint damping / dry friction /
    armature on the actuated joints; a motor-constant factor on the actuator force (gain, bias and
    force limit); a factor on the force limit alone; a factor on the servo stiffness; a factor on
    the sliding friction of every geom; a payload on the base (inertia scaled with the mass); a CoM
    shift of the base; a delay in seconds (rounded to the real time step); a servo dead band;
    any of the joint and actuator effects on some joints only (``damping@calf``, ``kp_scale@FR_``:
    the joints whose name holds the part after ``@``); out of library: a spring to the home angle,
    a quadratic drag.
    """
    all_jids = np.array([mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, j) for j in joints])
    body = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, base_body)
    ctl = Controller()
    for name, v in planted.items():
        x = np.asarray(v, float)
        name, _, part = name.partition("@")
        jids = all_jids
        if part:  # on some joints only: those whose name holds ``part`` (``calf``, ``FR_``)
            if name not in _ON_JOINTS:
                raise ValueError(f"planted {name}@{part}: only {_ON_JOINTS} take a joint part")
            jids = np.array([i for i, j in zip(all_jids, joints) if part in j])
            if not len(jids):
                raise ValueError(f"planted {name}@{part}: no joint of {joints} holds {part!r}")
        dofs = m.jnt_dofadr[jids]
        acts = np.flatnonzero((m.actuator_trntype == mujoco.mjtTrn.mjTRN_JOINT)
                              & np.isin(m.actuator_trnid[:, 0], jids))
        if name == "damping":
            m.dof_damping[dofs] += x
        elif name == "frictionloss":
            m.dof_frictionloss[dofs] += x
        elif name == "armature":
            m.dof_armature[dofs] += x
        elif name == "torque_scale":
            m.actuator_gainprm[acts, 0] *= x
            m.actuator_biasprm[acts, 1:3] *= x
            m.actuator_forcerange[acts] *= x
        elif name == "torque_limit":
            if not m.actuator_forcelimited[acts].astype(bool).all():
                raise ValueError("torque_limit needs force-limited actuators")
            m.actuator_forcerange[acts] *= x
        elif name == "kp_scale":
            m.actuator_gainprm[acts, 0] *= x
            m.actuator_biasprm[acts, 1] *= x
        elif name == "ground_friction":
            m.geom_friction[:, 0] *= x
        elif name == "contact_softness":
            m.geom_solref[:, 0] *= x
        elif name == "payload":
            m0 = float(m.body_mass[body])
            m.body_inertia[body] *= (m0 + float(x)) / m0
            m.body_mass[body] = m0 + float(x)
        elif name == "com_offset":
            m.body_ipos[body] += x
        elif name == "delay":
            ctl.delay_steps = int(round(float(x) / m.opt.timestep))
        elif name == "deadzone":
            ctl.deadband = float(x)
        elif name == "joint_stiffness":
            m.jnt_stiffness[jids] += x
            m.qpos_spring[m.jnt_qposadr[jids]] = m.qpos0[m.jnt_qposadr[jids]]
        elif name == "quadratic_drag":
            ctl.drag = float(x)
        else:
            raise ValueError(f"unknown planted effect {name!r}")
    return ctl


def _home(m: mujoco.MjModel) -> np.ndarray:
    k = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_KEY, "home")
    return m.key_qpos[k].copy() if k >= 0 else m.qpos0.copy()


_GAIT_OFFSETS = {"trot": (0.0, 0.5, 0.5, 0.0), "pronk": (0.0, 0.0, 0.0, 0.0), "bound": (0.0, 0.0, 0.5, 0.5),
                 "pace": (0.0, 0.5, 0.0, 0.5)}


def go1_reference(t: float, p: dict) -> np.ndarray:
    """``[12]`` joint targets (hip, thigh, calf per leg FR FL RR RL) of a gait at time ``t`` (s)."""
    phase = np.mod(p["freq"] * t + np.asarray(_GAIT_OFFSETS[p["gait"]]), 1.0)
    stance = phase < p["duty"]
    u = np.where(stance, phase / p["duty"], (phase - p["duty"]) / (1 - p["duty"]))
    sweep = np.where(stance, 1 - 2 * u, -1 + 2 * u)
    lift = np.where(stance, 0.0, np.sin(np.pi * u)) * p["lift"]
    side = np.array([-1.0, 1.0, -1.0, 1.0])
    hip = p["lateral"] * side
    thigh = 0.9 - p["stride"] * sweep + 0.5 * lift
    calf = -1.8 - lift
    return np.stack([hip, thigh, calf], 1).ravel()


def run_episode(m: mujoco.MjModel, ctl: Controller, robot, n_steps: int, rng: np.random.Generator,
                joints_dofs: np.ndarray, min_height: float = 0.12) -> dict[str, np.ndarray]:
    """One closed-loop episode of the "real" robot; returns ``t, q, qd, cmd, tau`` up to a fall."""
    d = mujoco.MjData(m)
    n_sub = int(round(robot.ctrl_dt / m.opt.timestep))
    q0 = _home(m)
    floating = robot.floating_base
    lo, hi = m.actuator_ctrlrange[:, 0], m.actuator_ctrlrange[:, 1]
    if floating:
        q0[2] += 0.02
        q0[7:] += 0.04 * rng.standard_normal(m.nu)
        gp = {"gait": str(rng.choice(list(_GAIT_OFFSETS))), "freq": rng.uniform(1.5, 3.0),
              "duty": rng.uniform(0.4, 0.65), "stride": rng.uniform(0.0, 0.3), "lift": rng.uniform(0.2, 0.7),
              "lateral": rng.uniform(-0.1, 0.1), "noise": rng.uniform(0.0, 0.08)}
    else:
        amp, freq, ph = (rng.uniform(0.2, 1.0, (3, m.nu)), rng.uniform(0.2, 2.0, (3, m.nu)),
                         rng.uniform(0, 2 * np.pi, (3, m.nu)))
    d.qpos[:] = q0
    mujoco.mj_forward(m, d)
    qadr = m.jnt_qposadr[m.actuator_trnid[:, 0]]
    servo = robot.kp is not None
    hist: list[np.ndarray] = []
    out = {k: [] for k in ("q", "qd", "cmd", "tau")}
    for t in range(n_steps):
        if floating:
            up = 1 - 2 * (d.qpos[4] ** 2 + d.qpos[5] ** 2)  # cos(tilt) from the quaternion
            if d.qpos[2] < min_height or up < np.cos(1.0) or not np.isfinite(d.qpos).all():
                break
            cmd = go1_reference(t * robot.ctrl_dt, gp) + gp["noise"] * rng.standard_normal(m.nu)
        else:
            tt = t * robot.ctrl_dt
            cmd = (amp * np.sin(2 * np.pi * freq * tt + ph)).sum(0) / 3 * hi
        cmd = np.clip(cmd, lo, hi)
        if servo and ctl.deadband:
            e = cmd - d.qpos[qadr]
            cmd_eff = d.qpos[qadr] + np.sign(e) * np.maximum(np.abs(e) - ctl.deadband, 0.0)
        else:
            cmd_eff = cmd
        hist.append(cmd_eff)
        out["q"].append(d.qpos.copy())
        out["qd"].append(d.qvel.copy())
        out["cmd"].append(cmd)
        out["tau"].append(d.actuator_force.copy())
        for k in range(n_sub):
            i = max(t * n_sub + k - ctl.delay_steps, 0) // n_sub
            d.ctrl[:] = hist[i]
            if ctl.drag:
                v = d.qvel[joints_dofs]
                d.qfrc_applied[:] = 0.0
                d.qfrc_applied[joints_dofs] = -ctl.drag * v * np.abs(v)
            mujoco.mj_step(m, d)
    return {k: np.array(v) for k, v in out.items()} | {"t": robot.ctrl_dt * np.arange(len(out["q"]))}


@dataclasses.dataclass(frozen=True)
class Go1Sensors:
    """A real Go1's sensors and state estimator (standard deviations).

    Attributes:
      encoder_res: joint encoder resolution (rad): the motor-side 15-bit encoder through the 9.1:1
        gear, ~2.1e-5 rad.
      velocity_std: joint velocity estimate noise (rad/s; differentiated motor encoders).
      glitch_rate: fraction of joint velocity samples replaced by a spike of 1-5 rad/s.
      torque_std: estimated torque noise (N m; from motor current).
      base_drift: estimator horizontal random walk (m per sample).
      base_z_std: estimator height noise (m).
      tilt_std: orientation noise (rad).
      linvel_std: estimator linear velocity noise (m/s).
      gyro_std: gyro noise (rad/s).
    """

    encoder_res: float = 2 * np.pi / 2 ** 15 / 9.1
    velocity_std: float = 0.04
    glitch_rate: float = 5e-4
    torque_std: float = 0.3
    base_drift: float = 1e-3
    base_z_std: float = 2e-3
    tilt_std: float = 3e-3
    linvel_std: float = 0.03
    gyro_std: float = 0.01

    def velocity_noise(self, sm) -> dict:
        """The log header's ``velocity_noise`` of these sensors (:mod:`stride_jax.gap.logs`):
        what a datasheet says of the white noise, not the glitches (the diagnosis's
        preprocessing takes those out)."""
        out = {"qd": self.velocity_std}
        if sm.robot.floating_base:
            out |= {"base_linvel": self.linvel_std, "base_angvel": self.gyro_std}
        return out


def sense(tr: logs.Trajectory, noise: Go1Sensors, floating: bool, qadr: np.ndarray, vadr: np.ndarray,
          rng: np.random.Generator) -> logs.Trajectory:
    """``tr`` as the sensors log it."""
    q, qd = tr.q.copy(), tr.qd.copy()
    T = len(q)
    q[:, qadr] = np.round(q[:, qadr] / noise.encoder_res) * noise.encoder_res
    v = qd[:, vadr] + noise.velocity_std * rng.standard_normal((T, len(vadr)))
    g = rng.random(v.shape) < noise.glitch_rate
    v[g] += rng.choice([-1.0, 1.0], g.sum()) * rng.uniform(1, 5, g.sum())
    qd[:, vadr] = v
    if floating:
        q[:, :2] += np.cumsum(noise.base_drift * rng.standard_normal((T, 2)), 0)
        q[:, 2] += noise.base_z_std * rng.standard_normal(T)
        half = 0.5 * noise.tilt_std * rng.standard_normal((T, 3))
        w, x, y, z = q[:, 3], q[:, 4], q[:, 5], q[:, 6]
        a, b, c = half.T
        quat = np.stack([w - x * a - y * b - z * c, w * a + x + y * c - z * b,
                         w * b - x * c + y + z * a, w * c + x * b - y * a + z], 1)
        q[:, 3:7] = quat / np.linalg.norm(quat, axis=1, keepdims=True)
        qd[:, :3] += noise.linvel_std * rng.standard_normal((T, 3))
        qd[:, 3:6] += noise.gyro_std * rng.standard_normal((T, 3))
    tau = None if tr.tau is None else tr.tau + noise.torque_std * rng.standard_normal(tr.tau.shape)
    return tr._replace(q=q, qd=qd, tau=tau)


def generate(robot_name: str, planted: dict[str, Any], seed: int, index: int, trajectories: int, steps: int,
             noisy: bool) -> tuple[list[logs.Trajectory], list[logs.Trajectory], dict, mujoco.MjModel]:
    """One case's logs: ``(clean, logged)`` trajectories of the "real" ``robot_name`` with the
    effects ``planted`` (at most ``trajectories`` episodes of ``steps`` control steps, those that
    stay up for 20 steps), its drawn simulator settings and the "real" model without the planted
    effects (for the effect's share of the gap). ``seed`` and ``index`` (the case's) seed the
    settings, the controller and the sensor noise (``noisy``: :class:`Go1Sensors`)."""
    from stride_jax import robots

    robot = robots.get(robot_name)
    rng = np.random.default_rng([seed, index])
    m = robot_spec(robot_name).compile()
    feet = [g for f in robot.feet for g in f.geoms]
    settings = draw_settings(m, rng, robot.ctrl_dt)
    set_simulator(m, settings, feet)
    form = copy.copy(m)  # MjModel's copy is a deep copy
    ctl = plant(m, planted, robot.joints, robot.base_body)
    dofs = m.jnt_dofadr[m.actuator_trnid[:, 0]]
    clean = []
    ep_rng = np.random.default_rng([seed, index, 1])
    for b in range(trajectories):
        ep = run_episode(m, ctl, robot, steps, ep_rng, dofs)
        if len(ep["q"]) < 20:
            continue
        clean.append(logs.Trajectory(f"traj_{b:03d}", ep["t"], ep["q"], ep["qd"], ep["cmd"], ep["tau"], None))
    if len(clean) < 2:
        raise RuntimeError(f"case {index} ({planted}, settings {settings}): fewer than 2 episodes "
                           "stayed up for 20 control steps")
    if not noisy:
        return clean, clean, settings, form
    qadr = m.jnt_qposadr[m.actuator_trnid[:, 0]]
    n_rng = np.random.default_rng([seed, index, 2])
    return clean, [sense(t, Go1Sensors(), robot.floating_base, qadr, dofs, n_rng) for t in clean], settings, form
