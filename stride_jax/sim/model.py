"""Compile a robot definition into an MJX-ready ``mujoco.MjModel`` plus the indices rollouts need."""

from __future__ import annotations

import dataclasses
import functools

import mujoco
import numpy as np

from stride_jax import robots as robots_lib
from stride_jax.robots import ModelInfo, Robot, RobotError


@dataclasses.dataclass(frozen=True, eq=False)
class SimModel:
    """A compiled robot.

    Attributes:
      robot: the definition it was compiled from.
      mj: the MJX-ready ``mujoco.MjModel`` (nominal: no randomisation applied).
      info: static facts for the explorer (home pose, control range, control period).
      n_substeps: simulation steps per control step.
      foot_geoms: ``[nfeet, G]`` geom ids of each foot, padded with -1.
      foot_sites: ``[nfeet]`` site ids at the soles.
      base_body: body id of the base.
      act_dof: ``[nu]`` dof index that each actuator drives.
      geom_foot: ``[ngeom]`` the foot each geom belongs to, or -1.
    """

    robot: Robot
    mj: mujoco.MjModel
    info: ModelInfo
    n_substeps: int
    foot_geoms: np.ndarray
    foot_sites: np.ndarray
    base_body: int
    act_dof: np.ndarray
    geom_foot: np.ndarray

    @property
    def nfeet(self) -> int:
        return len(self.robot.feet)


def _id(m: mujoco.MjModel, obj: mujoco.mjtObj, name: str, robot: str) -> int:
    if not name:  # mj_name2id segfaults on None; an empty name is never what we mean
        raise RobotError(f"robot {robot!r}: empty {obj.name} name in its definition")
    i = mujoco.mj_name2id(m, obj, name)
    if i < 0:
        raise RobotError(f"robot {robot!r}: no {obj.name.removeprefix('mjOBJ_').lower()} named "
                         f"{name!r} in the compiled model")
    return i


def body_id(sm: "SimModel", name: str, what: str = "body") -> int:
    """The id of ``sm``'s body ``name`` (``""``: the base body, where the IMU is); a name that
    is not one of the robot's bodies (the world included: nothing carries it) is a ``ValueError``
    that lists them, ``what`` naming what asked (``"payload body"``)."""
    if not name:
        return sm.base_body
    body = mujoco.mj_name2id(sm.mj, mujoco.mjtObj.mjOBJ_BODY, name)
    if body <= 0:  # -1: no such body; 0: the world
        names = [mujoco.mj_id2name(sm.mj, mujoco.mjtObj.mjOBJ_BODY, i) for i in range(1, sm.mj.nbody)]
        raise ValueError(f"{what} {name!r} is not a body of {sm.robot.name!r}; its bodies: "
                         f"{', '.join(names)}")
    return body


def strip_visual_meshes(spec: mujoco.MjSpec) -> int:
    """Deletes the mesh geoms that never collide (visual only) and the meshes left unused, where
    their bodies' inertia is given explicitly; returns how many geoms went.

    stride_jax never renders. The meshes and textures made a Go1 ``MjModel`` 42 MB (G1: 76 MB), so
    that a copy, one per randomised world, took ~120 ms (G1 ~190 ms) on this project's CPU. Masses,
    inertias, contacts and trajectories stay as they were (tested). Textures go too.
    """
    from_geom = spec.compiler.inertiafromgeom == mujoco.mjtInertiaFromGeom.mjINERTIAFROMGEOM_TRUE
    gone = 0
    for g in list(spec.geoms):
        body = g.parent
        if (g.type == mujoco.mjtGeom.mjGEOM_MESH and g.contype == 0 and g.conaffinity == 0
                and not from_geom and body.explicitinertial):
            spec.delete(g)
            gone += 1
    used = {g.meshname for g in spec.geoms if g.type == mujoco.mjtGeom.mjGEOM_MESH}
    for mesh in list(spec.meshes):
        if mesh.name not in used:
            spec.delete(mesh)
    for mat in spec.materials:  # textures (the skybox and the checker floor: 5 MB) only show
        mat.textures = [""] * len(mat.textures)
    for tex in list(spec.textures):
        spec.delete(tex)
    return gone


def _foot_maps(robot: Robot, m: mujoco.MjModel) -> tuple[np.ndarray, np.ndarray]:
    """``(foot_geoms [nfeet, G], geom_foot [ngeom])`` of ``robot``'s feet in ``m``, by name."""
    width = max((len(f.geoms) for f in robot.feet), default=0)
    foot_geoms = np.full((len(robot.feet), width), -1, dtype=np.int32)
    for i, foot in enumerate(robot.feet):
        for j, g in enumerate(foot.geoms):
            foot_geoms[i, j] = _id(m, mujoco.mjtObj.mjOBJ_GEOM, g, robot.name)
    geom_foot = np.full(m.ngeom, -1, dtype=np.int32)
    for i, geoms in enumerate(foot_geoms):
        geom_foot[geoms[geoms >= 0]] = i
    return foot_geoms, geom_foot


def on_model(sm: SimModel, m: mujoco.MjModel) -> SimModel:
    """``sm`` for ``m``, the same robot compiled again with other geoms (a heightfield beside the
    floor), which numbers its geoms differently: ``m`` itself and the feet's geom ids
    (``foot_geoms``, ``geom_foot``) read from it by name. Bodies, joints, sites and actuators
    must match (their ids are kept)."""
    for what in ("nbody", "njnt", "nsite", "nq", "nv", "nu"):
        if getattr(m, what) != getattr(sm.mj, what):
            raise RobotError(f"robot {sm.robot.name!r}: the model has {what} = "
                             f"{getattr(m, what)}, the robot's {getattr(sm.mj, what)}: only geoms "
                             f"may differ")
    foot_geoms, geom_foot = _foot_maps(sm.robot, m)
    return dataclasses.replace(sm, mj=m, foot_geoms=foot_geoms, geom_foot=geom_foot)


def compile_robot(robot: Robot, visual: bool = False) -> SimModel:
    """Parses, edits and compiles ``robot``; checks that its names match the model.

    ``visual=False`` leaves out the meshes that only show the robot (:func:`strip_visual_meshes`).
    """
    spec = robot.load_spec()
    robot.edit_spec(spec)
    if not visual:
        strip_visual_meshes(spec)
    m = spec.compile()
    n_sub = robot.ctrl_dt / m.opt.timestep
    if abs(n_sub - round(n_sub)) > 1e-6 or round(n_sub) < 1:
        raise RobotError(f"robot {robot.name!r}: ctrl_dt {robot.ctrl_dt} is not a multiple of the "
                         f"timestep {m.opt.timestep}")
    act_joints = [m.joint(m.actuator_trnid[i, 0]).name for i in range(m.nu)]
    if tuple(act_joints) != robot.joints:
        raise RobotError(f"robot {robot.name!r}: actuators drive {act_joints}, the definition "
                         f"lists {list(robot.joints)}")
    qpos0 = m.qpos0.copy()
    if robot.home_key is not None:
        qpos0 = m.key(_id(m, mujoco.mjtObj.mjOBJ_KEY, robot.home_key, robot.name)).qpos.copy()
    foot_geoms, geom_foot = _foot_maps(robot, m)
    foot_sites = np.array([_id(m, mujoco.mjtObj.mjOBJ_SITE, f.site, robot.name) for f in robot.feet],
                          dtype=np.int32)
    base = _id(m, mujoco.mjtObj.mjOBJ_BODY, robot.base_body, robot.name)
    info = ModelInfo(
        nq=m.nq, nv=m.nv, nu=m.nu, qpos0=qpos0.astype(np.float32),
        ctrl_lo=m.actuator_ctrlrange[:, 0].astype(np.float32),
        ctrl_hi=m.actuator_ctrlrange[:, 1].astype(np.float32),
        ctrl_dt=robot.ctrl_dt, base_body=base)
    return SimModel(robot=robot, mj=m, info=info, n_substeps=int(round(n_sub)),
                    foot_geoms=foot_geoms, foot_sites=foot_sites, base_body=base,
                    act_dof=m.jnt_dofadr[m.actuator_trnid[:, 0]].astype(np.int32),
                    geom_foot=geom_foot)


def load(name: str) -> SimModel:
    """The compiled robot called ``name``, or described by an MJCF / robot file at path ``name``
    (cached; a file is compiled again when its text changes). Raises RobotError for unknown or
    missing robots."""
    from stride_jax.robots import mjcf

    return _load(name, mjcf.file_key(name) if mjcf.is_path(name) else "")


@functools.lru_cache(maxsize=None)
def _load(name: str, key: str) -> SimModel:
    del key  # part of the cache key only
    return compile_robot(robots_lib.get(name))


def check_open_loop(sm: SimModel, qpos, qvel, ctrl) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Validates an open-loop rollout request: ``qpos [nq]``, ``qvel [nv]``, ``ctrl [T, nu]``."""
    m, name = sm.mj, sm.robot.name
    qpos, qvel, ctrl = (np.asarray(x, dtype=np.float64) for x in (qpos, qvel, ctrl))
    if qpos.shape != (m.nq,):
        raise ValueError(f"{name}: qpos has shape {list(qpos.shape)}, expected [{m.nq}]")
    if qvel.shape != (m.nv,):
        raise ValueError(f"{name}: qvel has shape {list(qvel.shape)}, expected [{m.nv}]")
    if ctrl.ndim != 2 or ctrl.shape[0] < 1 or ctrl.shape[1] != m.nu:
        raise ValueError(f"{name}: ctrl has shape {list(ctrl.shape)}, expected [T >= 1, {m.nu}]")
    for label, x in (("qpos", qpos), ("qvel", qvel), ("ctrl", ctrl)):
        if not np.isfinite(x).all():
            bad = np.argwhere(~np.isfinite(x))[0].tolist()
            raise ValueError(f"{name}: {label} contains NaN or inf (first at index {bad})")
    return qpos, qvel, ctrl


def robot_meta(sm: SimModel) -> dict:
    """What a dynamics model needs to know about a robot (coordinates, servos, timing): the part
    of a dataset's ``meta.json`` that describes the robot rather than the data."""
    m = sm.mj
    return dict(
        robot=sm.robot.name, source=sm.robot.source, nq=m.nq, nv=m.nv,
        sim_dt=float(m.opt.timestep), ctrl_dt=sm.robot.ctrl_dt, n_substeps=sm.n_substeps,
        joints=list(sm.robot.joints), feet=[f.name for f in sm.robot.feet],
        floating_base=sm.robot.floating_base,
        kp=list(sm.robot.kp) if sm.robot.kp else None,
        kd=list(sm.robot.kd) if sm.robot.kd else None,
        actuator_force_range=m.actuator_forcerange.tolist(),
        act_dof=sm.act_dof.tolist(),
        periodic=[bool(m.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE and not m.jnt_limited[j])
                  for j in range(m.njnt) if m.jnt_type[j] != mujoco.mjtJoint.mjJNT_FREE],
        ctrl_range=m.actuator_ctrlrange.tolist(),
        total_mass=float(m.body_mass.sum()),
    )
