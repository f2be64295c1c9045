"""Closed-loop scenarios: a command schedule and the ground (slope, friction, softness, terrain).

Scenarios: velocity step 0 -> 2 m/s, sudden command changes, a 20 degree slope (gravity tilted by
20 degrees about the y axis: on a plane this is the same physics as a tilted floor, walking +x is
uphill), the same slope reached by tilting the ground under the walking robot over its first two
seconds (``tilt``: a robot that starts on the full slope starts leaning 20 degrees back, which a
quadruped survives and a humanoid does not), ground unseen in training: low friction, soft
contacts, rough terrain (a heightfield), and lateral pushes on the base while walking.
"""

from __future__ import annotations

import copy
import dataclasses

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from stride_jax.sim import model as sim_model, randomize, terrain


@dataclasses.dataclass(frozen=True)
class Scenario:
    """A command schedule and the ground.

    Attributes:
      name: label.
      commands: ``(t_start s, vx m/s, vy m/s, yaw rad/s)`` pieces, piecewise constant.
      seconds: duration.
      slope_deg: ground slope, uphill along +x (gravity tilted about y).
      tilt_s: seconds over which the slope builds up from level, linearly (a tilting platform
        under the walking robot); 0: the slope is there from the first step.
      friction: scale of every geom's sliding friction.
      softness: scale of the contact time constant (solref[0]); > 1 is softer.
      rough_m: peak-to-peak height of a random heightfield replacing the floor (m); 0: flat.
      pushes: ``(t_start s, duration s, dvx m/s, dvy m/s)`` horizontal pushes on the base body,
        given as the velocity change they would give the whole robot (force = total mass x dv /
        duration), so that one scenario pushes a 12 kg quadruped and a 35 kg humanoid alike.
      payload: a load the robot carries that no model was told of: mass added to the base body
        as this fraction of the robot's total mass (its rotational inertia scaled with it, its
        centre of mass kept), so that one scenario loads both robots alike (0.25: 3.2 kg on the
        Go1, 8.3 kg on the G1). 0: none.
      payload_body: the body that carries it, by name ("": the base body, where the IMU is; a
        humanoid's backpack sits on its torso: ``torso_link`` on the G1).
    """

    name: str
    commands: tuple[tuple[float, float, float, float], ...]
    seconds: float = 6.0
    slope_deg: float = 0.0
    tilt_s: float = 0.0
    friction: float = 1.0
    softness: float = 1.0
    rough_m: float = 0.0
    pushes: tuple[tuple[float, float, float, float], ...] = ()
    payload: float = 0.0
    payload_body: str = ""

    def __post_init__(self):
        if not (np.isfinite(self.payload) and self.payload >= 0):
            raise ValueError(f"scenario {self.name!r}: payload={self.payload} must be a finite "
                             "fraction >= 0 of the robot's total mass")
        if self.payload_body and not self.payload:
            raise ValueError(f"scenario {self.name!r}: payload_body={self.payload_body!r} names "
                             "a body for a payload of 0")


WALK = ((0.0, 1.0, 0.0, 0.0),)
SCENARIOS = {
    "walk": Scenario("walk", WALK),
    "step": Scenario("step", ((0.0, 0.0, 0.0, 0.0), (1.0, 2.0, 0.0, 0.0))),
    "changes": Scenario("changes", ((0.0, 1.0, 0.0, 0.0), (1.5, 0.3, 0.4, 0.0),
                                    (3.0, 1.5, 0.0, 0.8), (4.5, 0.0, 0.0, 0.0))),
    "slope": Scenario("slope", WALK, slope_deg=20.0),
    "tilt": Scenario("tilt", WALK, slope_deg=20.0, tilt_s=2.0),
    "low_friction": Scenario("low_friction", WALK, friction=0.3),
    "soft": Scenario("soft", WALK, softness=4.0),
    "rough": Scenario("rough", WALK, rough_m=0.04),
    "push": Scenario("push", WALK, pushes=((2.0, 0.1, 0.0, 0.5), (4.0, 0.1, 0.0, -0.5))),
    "payload": Scenario("payload", WALK, payload=0.25),
}


def governed(sc: Scenario, bounds) -> Scenario:
    """``sc`` with every command clipped to ``bounds = (lo [3], hi [3])``: what the closed
    loop's command governor (``--govern``) shows the controller, as a schedule, for analyses that
    replay the policy alone (its scores still compare with the command asked for)."""
    lo, hi = (np.asarray(b, float) for b in bounds)
    return dataclasses.replace(sc, commands=tuple(
        (c[0],) + tuple(float(x) for x in np.clip(c[1:], lo, hi)) for c in sc.commands))


def scenario_model(sm: sim_model.SimModel, sc: Scenario, seed: int = 0) -> mujoco.MjModel:
    """The robot's MjModel with the scenario's ground and payload (a copy; the nominal model is
    untouched)."""
    if sc.rough_m > 0:
        spec = sm.robot.load_spec()
        sm.robot.edit_spec(spec)
        # as sim.model.compile_robot does, so that geom ids (the feet's contact flags) match sm's
        sim_model.strip_visual_meshes(spec)
        n, half = 64, 4.0  # 8 m x 8 m, 12.5 cm cells
        h = np.random.default_rng(seed).uniform(0, 1, (n, n))
        h[:, : n // 8 + 1] = 0.0  # a flat start area around the robot
        spec.add_hfield(name="rough", size=[half, half, sc.rough_m, 0.1], nrow=n, ncol=n,
                        userdata=h.reshape(-1).tolist())
        floor = next(g for g in spec.geoms if g.name == "floor")
        field = spec.worldbody.add_geom(name="rough", type=mujoco.mjtGeom.mjGEOM_HFIELD,
                                        hfieldname="rough", pos=[half - 1.0, 0, 0])
        terrain.hand_floor_over(spec, floor, field)  # G1's feet collide through pairs
        m = spec.compile()
    else:
        m = copy.copy(sm.mj)
    if sc.slope_deg:
        m.opt.gravity[:] = tilted(m.opt.gravity, np.deg2rad(sc.slope_deg), xp=np)
    m.geom_friction[:], m.pair_friction[:] = randomize.sliding_friction(
        m.geom_friction, m.pair_friction, np.float64(sc.friction), np)
    m.geom_solref[:], m.pair_solref[:] = randomize.contact_softness(
        m.geom_solref, m.pair_solref, np.float64(sc.softness), np)
    if sc.payload:
        randomize.add_payload(m, payload_body(sm, sc), sc.payload * float(sm.mj.body_mass.sum()))
        mujoco.mj_setConst(m, mujoco.MjData(m))  # the derived masses (subtree, mean inertia)
    return m


def payload_body(sm: sim_model.SimModel, sc: Scenario) -> int:
    """The id of the body that carries ``sc``'s payload: ``sc.payload_body`` by name, or the
    robot's base body; an unknown name is an error that lists the robot's bodies."""
    return sim_model.body_id(sm, sc.payload_body, f"scenario {sc.name!r}: payload body")


def tilt_schedule(sc: Scenario) -> np.ndarray:
    """The scenario's slope as ``[slope rad, seconds to build up]`` for :func:`gravity_at` (an
    array, so that scenarios share one compiled episode)."""
    return np.array([np.deg2rad(sc.slope_deg), sc.tilt_s], np.float32)


def tilted(gravity, slope, heading=0.0, xp=jnp):
    """The gravity ``[3]`` (``gravity``'s magnitude) under which a level floor is a slope of
    ``slope`` rad, uphill along ``heading`` rad from +x (0: about y, walking +x is uphill). The
    one place the project tilts gravity: the ``slope`` scenario's model, the ``tilt`` scenario's
    ramp (:func:`gravity_at`) and PPO's randomised slopes."""
    s = xp.sin(slope)
    return xp.linalg.norm(gravity) * xp.stack([-s * xp.cos(heading), -s * xp.sin(heading),
                                               -xp.cos(slope)])


def gravity_at(tilt: jax.Array, t: jax.Array, gravity: jax.Array,
               heading: jax.Array | float = 0.0) -> jax.Array:
    """The gravity ``[3]`` at time ``t`` (s) of a :func:`tilt_schedule`: level gravity (the
    magnitude of ``gravity``, the scenario model's own) :func:`tilted` by the slope times
    ``min(1, t / seconds)`` (uphill along ``heading``); ``gravity`` itself where the slope does
    not build up (seconds 0)."""
    tilt, gravity = jnp.asarray(tilt), jnp.asarray(gravity)
    slope, seconds = tilt[0], tilt[1]
    th = slope * jnp.clip(t / jnp.maximum(seconds, 1e-9), 0.0, 1.0)
    return jnp.where(seconds > 0, tilted(gravity, th, heading).astype(gravity.dtype), gravity)


def world_at(mx, d, base: int, t: jax.Array, pushes: jax.Array | None = None,
             tilt: jax.Array | None = None):
    """The scenario's world for the control period from time ``t`` (s): ``(mx, d)`` with the
    pushes of a :func:`push_schedule` on body ``base`` (``d.xfrc_applied``) and the gravity of a
    :func:`tilt_schedule` (``mx.opt.gravity``); either left as it is where not given."""
    if pushes is not None:
        d = d.replace(xfrc_applied=d.xfrc_applied.at[base, :2].set(push_at(pushes, t)))
    if tilt is not None:
        mx = mx.replace(opt=mx.opt.replace(gravity=gravity_at(tilt, t, mx.opt.gravity)))
    return mx, d


def schedule(sc: Scenario, pieces: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """The scenario's commands as arrays ``(starts [pieces], values [pieces, 3])``, padded with
    the last piece, so that scenarios share one compiled episode."""
    if len(sc.commands) > pieces:
        raise ValueError(f"scenario {sc.name!r} has more than {pieces} command pieces")
    c = list(sc.commands) + [sc.commands[-1]] * (pieces - len(sc.commands))
    return (np.array([x[0] for x in c], np.float32), np.array([x[1:] for x in c], np.float32))


def push_schedule(sc: Scenario, total_mass: float, slots: int = 4) -> np.ndarray:
    """The scenario's pushes as ``[slots, 4]`` rows ``(t_start, t_end, fx N, fy N)``, padded with
    zero-force rows, so that scenarios share one compiled episode."""
    if len(sc.pushes) > slots:
        raise ValueError(f"scenario {sc.name!r} has more than {slots} pushes")
    rows = [(t, t + dur, total_mass * dvx / dur, total_mass * dvy / dur)
            for t, dur, dvx, dvy in sc.pushes]
    rows += [(0.0, 0.0, 0.0, 0.0)] * (slots - len(rows))
    return np.array(rows, np.float32)


def push_at(pushes: jax.Array, t: jax.Array) -> jax.Array:
    """The horizontal force ``[2]`` (N) on the base at time ``t`` (s) of a :func:`push_schedule`."""
    pushes = jnp.asarray(pushes)
    on = (t >= pushes[:, 0]) & (t < pushes[:, 1])
    return jnp.sum(jnp.where(on[:, None], pushes[:, 2:4], 0.0), axis=0)


def command_at(starts: jax.Array, values: jax.Array, t: jax.Array) -> jax.Array:
    """The command ``[3]`` at time ``t`` (s) of a :func:`schedule`."""
    starts, values = jnp.asarray(starts), jnp.asarray(values)
    i = jnp.clip(jnp.searchsorted(starts, t, side="right") - 1, 0, starts.shape[0] - 1)
    return values[i]
