"""Hidden randomisation: sample values, apply them to a model (MJX or MuJoCo).

The same :func:`apply_fields` edits the model arrays for both backends (``xp`` is ``jax.numpy`` for
MJX, ``numpy`` for ``mujoco.MjModel`` copies), so the two simulate the same randomised worlds.
Most values are drawn per episode; the ground can also vary along the path (``patch_m > 0``):
each foot then takes the friction and softness of the ground patch under it, looked up from the
feet's positions at every control step (:func:`foot_patches`, :func:`apply_ground`).
Derived constants (``body_subtreemass``, ``dof_invweight0`` ...) are deliberately not recomputed
after a payload change, in both backends alike, as MuJoCo Playground does.
"""

from __future__ import annotations

import copy
from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from stride_jax.robots import Randomization
from stride_jax.sim import model as sim_model

FIELDS = ("geom_friction", "pair_friction", "geom_solref", "pair_solref", "body_mass",
          "dof_damping", "dof_frictionloss")


class RandValues(NamedTuple):
    """One episode's hidden parameters (scalars unless noted). For analysis only."""

    friction: jax.Array  # scale of sliding friction
    softness: jax.Array  # scale of the contact time constant
    payload_kg: jax.Array  # mass added to the payload's body (Randomization.payload_body)
    damping: jax.Array  # scale of joint damping
    frictionloss: jax.Array  # scale of joint dry friction
    bump_nm: jax.Array  # signed amplitude of the hidden joint torque bump (N m)
    push_t: jax.Array  # push start (s)
    push_s: jax.Array  # push duration (s)
    push_force: jax.Array  # [3] world-frame push force on the base (N)
    extra_push_t: jax.Array  # [pushes - 1] start of each further push (s)
    extra_push_s: jax.Array  # [pushes - 1] durations (s)
    extra_push_force: jax.Array  # [pushes - 1, 3] world-frame forces (N)
    terrain_seed: jax.Array  # uint32: the episode's ground patches (see foot_patches)
    down: jax.Array  # [3] gravity's direction in the floor's frame (unit; -z unless sloped)


def sample(key: jax.Array, r: Randomization, episode_s: float) -> RandValues:
    """Draws one episode's values, uniformly in the ranges of ``r``."""
    ks = jax.random.split(key, 11)
    u = lambda k, rng: jax.random.uniform(k, minval=rng[0], maxval=rng[1])
    sign = jnp.where(jax.random.bernoulli(ks[6]), 1.0, -1.0)
    heading = jax.random.uniform(ks[9], minval=-jnp.pi, maxval=jnp.pi)
    push = u(ks[8], r.push_n) * (r.pushes > 0)
    # Draws added later come from a key of their own, so the older draws stay as they were.
    kx = jax.random.split(jax.random.fold_in(key, 1), 5)
    n = max(r.pushes - 1, 0)
    ux = lambda k, rng: jax.random.uniform(k, (n,), minval=rng[0], maxval=rng[1])
    heading_x = ux(kx[0], (-jnp.pi, jnp.pi))
    ks_slope = jax.random.split(jax.random.fold_in(key, 2), 2)
    tilt = jnp.deg2rad(u(ks_slope[0], r.slope_deg))
    downhill = jax.random.uniform(ks_slope[1], minval=-jnp.pi, maxval=jnp.pi)
    return RandValues(
        friction=u(ks[0], r.friction),
        softness=u(ks[1], r.softness),
        payload_kg=u(ks[2], r.payload_kg),
        damping=u(ks[3], r.damping),
        frictionloss=u(ks[4], r.frictionloss),
        bump_nm=sign * u(ks[5], r.bump_nm),
        push_t=u(ks[7], (0.2 * episode_s, 0.8 * episode_s)),
        push_s=u(ks[10], r.push_s),
        push_force=push * jnp.array([jnp.cos(heading), jnp.sin(heading), 0.0]),
        extra_push_t=ux(kx[1], (0.05 * episode_s, 0.95 * episode_s)),
        extra_push_s=ux(kx[2], r.push_s),
        extra_push_force=ux(kx[3], r.push_n)[:, None] * jnp.stack(
            [jnp.cos(heading_x), jnp.sin(heading_x), jnp.zeros(n)], axis=-1),
        terrain_seed=jax.random.bits(kx[4], (), jnp.uint32),
        down=jnp.stack([jnp.sin(tilt) * jnp.cos(downhill), jnp.sin(tilt) * jnp.sin(downhill),
                        -jnp.cos(tilt)]),
    )


def sliding_friction(geom_friction, pair_friction, factor, xp=jnp):
    """``(geom_friction, pair_friction)`` with their sliding friction scaled by ``factor`` (a
    scalar, traced or not): geoms hold (slide, spin, roll), explicit contact pairs (slide1,
    slide2, spin, roll1, roll2). The one place the project scales a ground's friction: the
    hidden randomisation, the closed loop's low-friction scenario and PPO's randomised ground."""
    one = xp.ones_like(factor)
    return (geom_friction * xp.stack([factor, one, one]),
            pair_friction * xp.stack([factor, factor, one, one, one]))


def contact_softness(geom_solref, pair_solref, factor, xp=jnp):
    """``(geom_solref, pair_solref)`` with the contact time constant (``solref[0]``) scaled by
    ``factor`` (> 1: softer ground; a scalar, traced or not), the damping ratio kept. The one place
    the project softens a ground: the hidden randomisation, the closed loop's soft scenario and
    PPO's randomised ground."""
    one = xp.ones_like(factor)
    scale = xp.stack([factor, one])
    return geom_solref * scale, pair_solref * scale


def apply_fields(fields: dict, v: RandValues, payload_body: int, xp=jnp) -> dict:
    """Returns the model arrays of :data:`FIELDS` with the episode's values applied; the payload
    on body ``payload_body`` (:func:`payload_body_id`)."""
    f = dict(fields)
    f["geom_friction"], f["pair_friction"] = sliding_friction(
        fields["geom_friction"], fields["pair_friction"], v.friction, xp)
    f["geom_solref"], f["pair_solref"] = contact_softness(
        fields["geom_solref"], fields["pair_solref"], xp.asarray(v.softness), xp)
    f["body_mass"] = fields["body_mass"] + v.payload_kg * (xp.arange(fields["body_mass"].shape[0])
                                                           == payload_body)
    f["dof_damping"] = fields["dof_damping"] * v.damping
    f["dof_frictionloss"] = fields["dof_frictionloss"] * v.frictionloss
    return f


def payload_fields(body_mass, body_inertia, body: int, kg, xp=jnp):
    """``(body_mass, body_inertia)`` with ``kg`` added to body ``body``, its rotational inertia
    scaled with its mass and its centre of mass kept (a load strapped on). ``kg`` may be traced
    (one per world under ``vmap``: PPO's randomised payload); ``xp`` as in :func:`apply_fields`.
    The one place the project straps a load on: :func:`add_payload` and the env's
    (``stride_jax.control.envs.with_payload``)."""
    hit = xp.arange(body_mass.shape[0]) == body
    m0 = body_mass[body]
    scale = xp.where(hit, (m0 + kg) / m0, 1.0)
    return body_mass + xp.where(hit, kg, 0.0), body_inertia * scale[:, None]


def check_payload_body(body_mass, body: int, what: str = "payload body") -> None:
    """A body that carries a load scaled with it (:func:`payload_fields`) needs a mass: a
    massless one (a frame, a site holder) would take an infinite inertia; an error naming it."""
    if not float(body_mass[body]) > 0:
        raise ValueError(f"{what}: body {body} has no mass, so a load scaled with it has no "
                         "inertia to scale; put the load on a body with mass")


def add_payload(m: mujoco.MjModel, body: int, kg: float) -> None:
    """Adds ``kg`` to body ``body`` of ``m`` in place (:func:`payload_fields`: the gap tool's
    ``payload`` effect and the closed loop's ``payload`` scenario). Derived constants are left
    to the caller, as :func:`apply_fields` leaves them."""
    check_payload_body(m.body_mass, body, mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, body))
    m.body_mass[:], m.body_inertia[:] = payload_fields(m.body_mass, m.body_inertia, body,
                                                       float(kg), np)


def tilted_gravity(gravity, down, xp=jnp):
    """The gravity vector (m/s^2) of a model whose ``gravity`` is tilted to point along the
    unit vector ``down`` (its magnitude kept): the slope of
    :attr:`~stride_jax.robots.Randomization.slope_deg`, under a floor that stays the world's
    x-y plane."""
    return xp.linalg.norm(xp.asarray(gravity)) * down


def tilt_mjx(mx, down: jax.Array):
    """``mx`` with its gravity along ``down`` (an episode's ``RandValues.down``)."""
    g = tilted_gravity(mx.opt.gravity, down).astype(mx.opt.gravity.dtype)
    return mx.replace(opt=mx.opt.replace(gravity=g))


def tilt_mujoco(m: mujoco.MjModel, down: np.ndarray) -> None:
    """Tilts the gravity of ``m`` (a copy of its own: :func:`apply_mujoco`'s) along ``down``
    in place."""
    m.opt.gravity[:] = tilted_gravity(m.opt.gravity, np.asarray(down, np.float64), np)


def nominal_fields(m: mujoco.MjModel) -> dict:
    """The arrays of :data:`FIELDS` of a MuJoCo model."""
    return {k: np.array(getattr(m, k)) for k in FIELDS}


def payload_body_id(sm, r: Randomization | None = None) -> int:
    """The id of ``sm``'s body that carries the hidden payload of ``r`` (default: the robot's
    own randomisation; :attr:`~stride_jax.robots.Randomization.payload_body`, the base body
    when unnamed); a name the robot lacks is an error listing its bodies."""
    r = r if r is not None else sm.robot.randomization
    return sim_model.body_id(sm, r.payload_body, "randomization.payload_body")


def apply_mjx(mx, fields: dict, v: RandValues, payload_body: int):
    """An ``mjx.Model`` with the episode's values; vmap over ``v`` for a batch of worlds."""
    jfields = {k: jnp.asarray(a, dtype=jnp.float32) for k, a in fields.items()}
    return mx.replace(**{k: a.astype(getattr(mx, k).dtype)
                         for k, a in apply_fields(jfields, v, payload_body, jnp).items()})


def apply_mujoco(m: mujoco.MjModel, fields: dict, v: RandValues,
                 payload_body: int) -> mujoco.MjModel:
    """A randomised copy of ``m`` (``v`` holds one episode's values, as numpy or JAX scalars)."""
    out = copy.copy(m)  # MjModel's copy is a deep copy
    vals = RandValues(*(np.asarray(x, dtype=np.float64) for x in v))
    for k, a in apply_fields(fields, vals, payload_body, np).items():
        getattr(out, k)[...] = a
    return out


class Disturbance(NamedTuple):
    """Hidden external forces at one instant."""

    push: jax.Array  # [3] world-frame force on the base body (N)
    qfrc: jax.Array  # [nv] generalised force (qfrc_applied)


def disturbance(v: RandValues, r: Randomization, t: jax.Array, qpos: jax.Array,
                nv: int) -> Disturbance:
    """The episode's hidden external forces at time ``t`` (s) and configuration ``qpos``.

    A push is a rectangular force pulse on the base (``r.pushes`` of them, which may overlap).
    The bump is a torque on the first dof of a fixed-base robot, a Gaussian in the wrapped angle
    from ``r.bump_at`` (zero if unused).
    """
    on = (t >= v.push_t) & (t < v.push_t + v.push_s)
    push = jnp.where(on, v.push_force, 0.0)
    on_x = (t >= v.extra_push_t) & (t < v.extra_push_t + v.extra_push_s)
    push = push + jnp.sum(jnp.where(on_x[:, None], v.extra_push_force, 0.0), axis=0)
    angle = jnp.mod(qpos[0] - r.bump_at + jnp.pi, 2 * jnp.pi) - jnp.pi
    bump = v.bump_nm * jnp.exp(-0.5 * (angle / r.bump_width) ** 2)
    return Disturbance(push, jnp.zeros(nv).at[0].set(bump))


# -------------------------------------------------------------------------------------------
# Ground that varies along the path.

GROUND_FIELDS = ("geom_friction", "geom_solref", "pair_friction", "pair_solref")


def foot_patches(v: RandValues, r: Randomization, foot_xy: jax.Array
                 ) -> tuple[jax.Array, jax.Array]:
    """Friction and softness scales ``([F], [F])`` of the ground patches under the feet.

    ``foot_xy [F, 2]`` (m, world frame). The ground is a grid of ``r.patch_m`` squares; each
    square's two scales are uniform draws in ``r.patch_friction`` and ``r.patch_softness`` from a
    key made of the episode's ``terrain_seed`` and the square's integer coordinates, so the same
    place has the same ground whenever a foot comes back to it, in both backends.
    """
    cell = jax.lax.bitcast_convert_type(
        jnp.floor(foot_xy / r.patch_m).astype(jnp.int32), jnp.uint32)
    base = jax.random.key(v.terrain_seed)

    def one(c):
        u = jax.random.uniform(jax.random.fold_in(jax.random.fold_in(base, c[0]), c[1]), (2,))
        lerp = lambda rng, x: rng[0] + (rng[1] - rng[0]) * x
        return lerp(r.patch_friction, u[0]), lerp(r.patch_softness, u[1])

    return jax.vmap(one)(cell)


def apply_ground(fields: dict, geom_foot: np.ndarray, pair_foot: np.ndarray, friction,
                 softness, xp=jnp) -> dict:
    """The :data:`GROUND_FIELDS` of ``fields`` with foot ``i``'s contacts scaled by
    ``friction[i]`` (sliding) and ``softness[i]`` (time constant).

    ``geom_foot [ngeom]`` and ``pair_foot [npair]`` give the foot each geom or contact pair
    belongs to (-1: none). Geom-geom contacts take the foot's own values only in a model made by
    :func:`ground_ready` (the feet win MuJoCo's parameter combination by priority).
    """
    def per(index, values):
        index = np.asarray(index)
        return xp.where(xp.asarray(index >= 0), xp.asarray(values)[np.maximum(index, 0)], 1.0)

    fg, sg = per(geom_foot, friction), per(geom_foot, softness)
    fp, sp = per(pair_foot, friction), per(pair_foot, softness)
    og, op = xp.ones_like(fg), xp.ones_like(fp)
    f = dict(fields)
    f["geom_friction"] = fields["geom_friction"] * xp.stack([fg, og, og], axis=-1)
    f["geom_solref"] = fields["geom_solref"] * xp.stack([sg, og], axis=-1)
    f["pair_friction"] = fields["pair_friction"] * xp.stack([fp, fp, op, op, op], axis=-1)
    f["pair_solref"] = fields["pair_solref"] * xp.stack([sp, op], axis=-1)
    return f


def foot_xy(mx, foot_sites: np.ndarray, qpos: jax.Array) -> jax.Array:
    """``[F, 2]`` world positions (m) of the foot sites at ``qpos``: MJX's kinematics, used by
    both backends so that they look up the same patches."""
    d = mjx.kinematics(mx, mjx.make_data(mx).replace(qpos=qpos))
    return d.site_xpos[foot_sites, :2]


def pair_feet(m: mujoco.MjModel, geom_foot: np.ndarray) -> np.ndarray:
    """``[npair]`` the foot each explicit contact pair touches with (-1: none)."""
    g1, g2 = np.asarray(m.pair_geom1, int), np.asarray(m.pair_geom2, int)
    return np.where(geom_foot[g1] >= 0, geom_foot[g1], geom_foot[g2]).astype(np.int32)


def ground_ready(m: mujoco.MjModel, geom_foot: np.ndarray) -> mujoco.MjModel:
    """A copy of ``m`` in which each foot geom's geom-geom contacts take the foot's own
    parameters, with the same contacts as ``m``.

    MuJoCo combines two geoms' parameters (friction: max; solref, solimp: mixed by solmix), so a
    foot's friction alone cannot lower its contacts' friction. The copy raises each colliding foot
    geom's priority above the geoms it touches, whose parameters then apply as they are, and gives
    it the combined values, so nothing changes until :func:`apply_ground` scales them. Explicit
    pairs carry their own parameters and need nothing.
    """
    out = copy.copy(m)
    feet = np.flatnonzero(geom_foot >= 0)
    others = np.flatnonzero(geom_foot < 0)
    for f in feet:
        touch = [g for g in others if (m.geom_contype[f] & m.geom_conaffinity[g])
                 or (m.geom_contype[g] & m.geom_conaffinity[f])]
        if not touch:
            continue
        params = lambda g: (tuple(m.geom_friction[g]), tuple(m.geom_solref[g]),
                            tuple(m.geom_solimp[g]), float(m.geom_solmix[g]),
                            int(m.geom_priority[g]), int(m.geom_condim[g]))
        if len({params(g) for g in touch}) > 1:
            names = [m.geom(int(g)).name or f"geom {g}" for g in touch]
            raise ValueError(f"ground patches: foot geom {m.geom(int(f)).name!r} touches geoms "
                             f"with different contact parameters ({names}); give them the same "
                             "parameters or use explicit contact pairs")
        g = touch[0]
        if m.geom_priority[g] > m.geom_priority[f]:
            src = g
        elif m.geom_priority[g] < m.geom_priority[f]:
            continue  # the foot's own values apply already
        else:
            src = None
        if src is not None:
            fr, ref, imp, dim = (m.geom_friction[g], m.geom_solref[g], m.geom_solimp[g],
                                 m.geom_condim[g])
        else:  # equal priority: MuJoCo's combination (engine_collision_driver.c, mj_contactParam)
            s1, s2, eps = float(m.geom_solmix[f]), float(m.geom_solmix[g]), mujoco.mjMINVAL
            mix = 0.5 if s1 < eps and s2 < eps else (0.0 if s1 < eps else (
                1.0 if s2 < eps else s1 / (s1 + s2)))
            fr = np.maximum(m.geom_friction[f], m.geom_friction[g])
            r1, r2 = m.geom_solref[f], m.geom_solref[g]
            ref = mix * r1 + (1 - mix) * r2 if r1[0] > 0 and r2[0] > 0 else np.minimum(r1, r2)
            imp = mix * m.geom_solimp[f] + (1 - mix) * m.geom_solimp[g]
            dim = max(m.geom_condim[f], m.geom_condim[g])
        out.geom_friction[f], out.geom_solref[f], out.geom_solimp[f] = fr, ref, imp
        out.geom_condim[f] = dim
        out.geom_priority[f] = m.geom_priority[g] + 1
    return out
