"""Rough ground: a MuJoCo heightfield whose heights are drawn per episode.

With ``Randomization.rough_m`` above zero, the robot walks on a heightfield (``<hfield>`` asset,
an hfield geom named ``rough``) instead of the flat floor: the floor keeps its place and looks but
collides with nothing, and the heightfield takes its contact parameters, its contact types and
its explicit contact pairs (G1's feet), so the feet-only contact set stays as it was. MJX
collides heightfields with spheres (Go1's feet), capsules (G1's feet), boxes and meshes
(``mujoco/mjx/_src/collision_driver.py``); each foot-heightfield pair takes 4 contact slots.
MJX has no contact margin for heightfields, so the geoms touching the ground lose theirs (Go1's
feet had 1 mm).

The field is a square of side ``2 rough_extent_m`` sampled every ``rough_cell_m`` (the model's
shape is static; only the heights change per episode and world). Its heights are a smooth random
field (random Fourier features of a squared-exponential kernel whose length scale is drawn per
episode in ``rough_scale_m``), with standard deviation ``A / 2`` clipped at ``+-A``, ``A`` drawn
per episode in ``rough_m``. Everything is drawn from the episode's ``terrain_seed``, so both
backends simulate the same ground. The field is lowered so that the ground within
:data:`START_RADIUS` of the origin, where the robots start, lies at or below the flat floor's
level: the feet start above the ground and settle onto it. A robot that walks off the field falls
(the episode's steps after that are marked invalid); choose ``rough_extent_m`` to cover the path.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from stride_jax.robots import Randomization, RobotError
from stride_jax.sim import model as model_lib

NAME = "rough"
START_RADIUS = 0.4  # m: the ground within this distance of the origin is at or below z = 0
FEATURES = 64  # random Fourier features of one field
BASE_M = 0.1  # depth of the heightfield's prisms below its lowest level (m)
_SALT = 0x52_6F_75_67  # "Roug": the field's key, apart from the patches' keys


def grid_size(r: Randomization) -> int:
    """Points along each side of the field."""
    return round(2 * r.rough_extent_m / r.rough_cell_m) + 1


def add_heightfield(spec: mujoco.MjSpec, r: Randomization) -> None:
    """Adds the heightfield to ``spec`` in place of the floor's collisions (see module doc)."""
    floors = [g for g in spec.worldbody.geoms if g.type == mujoco.mjtGeom.mjGEOM_PLANE]
    if len(floors) != 1:
        raise RobotError(f"rough ground replaces the floor: the model has {len(floors)} plane "
                         "geoms in its world body, expected exactly one")
    floor = floors[0]
    n, top = grid_size(r), r.rough_m[1]
    spec.add_hfield(name=NAME, size=[r.rough_extent_m, r.rough_extent_m, 4 * top, BASE_M],
                    nrow=n, ncol=n, userdata=[0.5] * (n * n))
    g = spec.worldbody.add_geom(type=mujoco.mjtGeom.mjGEOM_HFIELD, hfieldname=NAME, name=NAME,
                                pos=[0, 0, -2 * top])
    hand_floor_over(spec, floor, g)


def hand_floor_over(spec: mujoco.MjSpec, floor, field) -> None:
    """Gives the floor geom's collisions to ``field`` (a heightfield geom added in its place):
    the floor's contact settings are copied, the floor stops colliding, its explicit pairs move to
    the field, and the geoms that touch the ground lose their margin and gap. One handover for the
    data's rough ground and the closed loop's, so both see the same contact."""
    for attr in ("contype", "conaffinity", "condim", "priority", "friction", "solref", "solimp",
                 "solmix"):
        setattr(field, attr, getattr(floor, attr))
    # MJX has no contact margin for heightfields (mjx/_src/io.py): the geoms that touch the
    # ground lose theirs (Go1's feet: 1 mm).
    for other in spec.geoms:
        if other is not floor and other is not field and (
                (other.contype & floor.conaffinity) or (other.conaffinity & floor.contype)):
            other.margin, other.gap = 0.0, 0.0
    floor.contype, floor.conaffinity = 0, 0
    retarget_pairs(spec, floor.name, field.name)


def retarget_pairs(spec: mujoco.MjSpec, old: str, new: str) -> None:
    """Moves the explicit contact pairs (``<pair>``: G1's feet with the floor) of geom ``old`` to
    geom ``new``, a heightfield taking the floor's place, with no margin or gap (MJX has none for
    heightfields). Pairs ignore ``contype``/``conaffinity``: without this the feet keep colliding
    with the switched-off floor and never meet the heightfield."""
    for pair in spec.pairs:
        if old in (pair.geomname1, pair.geomname2):
            pair.geomname1 = new if pair.geomname1 == old else pair.geomname1
            pair.geomname2 = new if pair.geomname2 == old else pair.geomname2
            pair.margin, pair.gap = 0.0, 0.0


@functools.lru_cache(maxsize=None)
def rough_model(sm: model_lib.SimModel, r: Randomization) -> model_lib.SimModel:
    """``sm`` compiled again with the heightfield of ``r`` (cached per model and ranges)."""
    if not r.rough:
        return sm
    robot = sm.robot
    edit = lambda spec: (robot.edit_spec(spec), add_heightfield(spec, r))
    out = model_lib.compile_robot(dataclasses.replace(robot, edit_spec=edit))
    return dataclasses.replace(out, robot=robot)


def heights(terrain_seed: jax.Array, r: Randomization) -> jax.Array:
    """``[n * n]`` the heightfield's data (MuJoCo's layout: row ``i`` at ``y_i``, column ``j`` at
    ``x_j``, scaled to the field's elevation range) of the episode with ``terrain_seed``."""
    return to_data(height_grid(terrain_seed, r), r).reshape(-1)


def height_grid(terrain_seed: jax.Array, r: Randomization) -> jax.Array:
    """``[n, n]`` ground heights (m) at ``(y_i, x_j)`` of :func:`grid_points`."""
    key = jax.random.fold_in(jax.random.key(terrain_seed), _SALT)
    ka, kl, kw, kp = jax.random.split(key, 4)
    amp = jax.random.uniform(ka, minval=r.rough_m[0], maxval=r.rough_m[1])
    scale = jax.random.uniform(kl, minval=r.rough_scale_m[0], maxval=r.rough_scale_m[1])
    w = jax.random.normal(kw, (FEATURES, 2)) / scale
    phase = jax.random.uniform(kp, (FEATURES,), maxval=2 * jnp.pi)
    x, y = grid_points(r)
    xy = jnp.stack(jnp.meshgrid(x, y), axis=-1)  # [n(y), n(x), 2]
    f = jnp.sqrt(2.0 / FEATURES) * jnp.cos(xy @ w.T + phase).sum(-1)  # unit variance
    h = jnp.clip(0.5 * amp * f, -amp, amp)
    near = (xy ** 2).sum(-1) <= START_RADIUS ** 2
    return h - jnp.max(jnp.where(near, h, -jnp.inf))


def grid_points(r: Randomization) -> tuple[np.ndarray, np.ndarray]:
    """``(x [n], y [n])`` the field's sample coordinates (m, world frame)."""
    p = np.linspace(-r.rough_extent_m, r.rough_extent_m, grid_size(r), dtype=np.float32)
    return p, p


def to_data(h: jax.Array, r: Randomization) -> jax.Array:
    """Heights (m, within ``+-2 max(rough_m)``) as MuJoCo's elevation data in [0, 1] of the
    geom made by :func:`add_heightfield` (placed ``2 max(rough_m)`` below the floor, elevation
    range ``4 max(rough_m)``)."""
    top = r.rough_m[1]
    return jnp.clip((h + 2 * top) / (4 * top), 0.0, 1.0)


def ground_height(m: mujoco.MjModel, xy) -> float:
    """Height (m) of the heightfield's surface at world ``xy`` as MuJoCo sees it (a ray cast
    down onto the heightfield geom; for tests and analysis)."""
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    g = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, NAME)
    top = 10.0
    dist = mujoco.mj_rayHfield(m, d, g, np.array([xy[0], xy[1], top]), np.array([0.0, 0.0, -1.0]))
    return top - dist if dist >= 0 else float("nan")
