"""What a robot is, for stride_jax: model source, joints, feet, control, and how to explore with it.

A :class:`Robot` is a frozen description; :func:`stride_jax.sim.model.load` turns it into an
MJX-ready ``mujoco.MjModel`` by applying the robot's ``edit_spec`` to the parsed ``mujoco.MjSpec``.
Exploration (how the data-collecting controller moves the robot) is part of the robot because it
is specific to its morphology: a gait library for the quadruped, balance and stepping for the
humanoid, random torques for the pendulum.
"""

from __future__ import annotations

import dataclasses
import os
import pathlib
from typing import Callable

import mujoco

from stride_jax.types import Explorer, ModelInfo  # the explorer's contract; re-exported

ASSETS = pathlib.Path(__file__).parent / "assets"


class RobotError(ValueError):
    """An unknown robot, or a robot whose model files cannot be found."""


@dataclasses.dataclass(frozen=True)
class Foot:
    """One contact end-effector: the collision geoms that touch the floor, and a site at its sole."""

    name: str
    geoms: tuple[str, ...]
    site: str


@dataclasses.dataclass(frozen=True)
class Randomization:
    """Hidden per-episode randomisation ranges (uniform). Models never see the sampled values.

    Attributes:
      friction: scale of the sliding friction of every contact, (lo, hi).
      softness: scale of the contact solref time constant (> 1 is softer), (lo, hi).
      payload_kg: mass added to ``payload_body`` (kg), (lo, hi): a point load at the body's
        centre of mass (its mass grows, its rotational inertia about that centre does not; the
        closed loop's ``payload`` scenario and PPO's ``payload_max`` scale the body instead).
      payload_body: the body that carries it, by name ("": the base body; a humanoid's
        backpack: G1's ``torso_link``).
      push_n: magnitude of one horizontal push on the base (N), (lo, hi); 0 disables pushes.
      push_s: duration of the push (s), (lo, hi).
      damping: scale of every joint's viscous damping, (lo, hi).
      frictionloss: scale of every joint's dry friction, (lo, hi).
      bump_nm: magnitude of a hidden torque on the first joint of a fixed-base robot, acting only
        near ``bump_at`` (a Gaussian bump of width ``bump_width`` in the wrapped angle), with a
        random sign per episode: a bimodal residual there (the pendulum's upright).
      pushes: number of pushes per episode (each with the ranges above, at its own time).
      patch_m: side of the square ground patches (m) whose friction and softness vary along the
        path, drawn per episode and per patch; each foot takes the patch under it, so two feet
        of one stance can stand on different ground. 0: the ground is uniform.
      patch_friction: scale of a patch's sliding friction on top of ``friction``, (lo, hi).
      patch_softness: scale of a patch's contact time constant on top of ``softness``, (lo, hi).
      rough_m: amplitude of the rough ground (m), (lo, hi), drawn per episode: the robot walks on
        a heightfield of smooth random bumps (height std amplitude / 2, clipped at +-amplitude;
        :mod:`stride_jax.sim.terrain`). (0, 0): the flat floor.
      rough_scale_m: length scale of the bumps (m), (lo, hi), drawn per episode.
      rough_extent_m: half side of the square heightfield (m), centred on the start; a robot
        that leaves it falls.
      rough_cell_m: spacing of the heightfield's samples (m).
      slope_deg: tilt of gravity under the floor (degrees), (lo, hi), drawn per episode with a
        downhill heading uniform in any direction: the robot walks a slope of that angle with
        the world frame the floor's (as the closed loop's slope scenarios emulate one). The
        records carry each step's gravity (``Record.gravity``). (0, 0): gravity as modelled.
    """

    friction: tuple[float, float] = (1.0, 1.0)
    softness: tuple[float, float] = (1.0, 1.0)
    payload_kg: tuple[float, float] = (0.0, 0.0)
    payload_body: str = ""
    push_n: tuple[float, float] = (0.0, 0.0)
    push_s: tuple[float, float] = (0.1, 0.2)
    damping: tuple[float, float] = (1.0, 1.0)
    frictionloss: tuple[float, float] = (1.0, 1.0)
    bump_nm: tuple[float, float] = (0.0, 0.0)
    bump_at: float = 0.0
    bump_width: float = 0.25
    pushes: int = 1
    patch_m: float = 0.0
    patch_friction: tuple[float, float] = (1.0, 1.0)
    patch_softness: tuple[float, float] = (1.0, 1.0)
    rough_m: tuple[float, float] = (0.0, 0.0)
    rough_scale_m: tuple[float, float] = (0.2, 0.5)
    rough_extent_m: float = 10.0
    rough_cell_m: float = 0.05
    slope_deg: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self):
        if self.pushes < 0 or self.patch_m < 0:
            raise ValueError(f"randomisation: pushes ({self.pushes}) and patch_m ({self.patch_m}) "
                             "must be >= 0")
        for name in ("friction", "softness", "patch_friction", "patch_softness"):
            lo, hi = getattr(self, name)
            if not 0 < lo <= hi:
                raise ValueError(f"randomisation: {name} range ({lo}, {hi}) must satisfy "
                                 "0 < lo <= hi")
        lo, hi = self.slope_deg
        if not 0 <= lo <= hi < 90:
            raise ValueError(f"randomisation: slope_deg range ({lo}, {hi}) must satisfy "
                             "0 <= lo <= hi < 90")
        lo, hi = self.rough_m
        if not 0 <= lo <= hi:
            raise ValueError(f"randomisation: rough_m range ({lo}, {hi}) must satisfy "
                             "0 <= lo <= hi")
        if self.rough:
            if not 0 < self.rough_scale_m[0] <= self.rough_scale_m[1]:
                raise ValueError(f"randomisation: rough_scale_m {self.rough_scale_m} must "
                                 "satisfy 0 < lo <= hi")
            if not 0 < self.rough_cell_m < self.rough_extent_m:
                raise ValueError(f"randomisation: rough_cell_m ({self.rough_cell_m}) must be "
                                 f"in (0, rough_extent_m = {self.rough_extent_m})")

    @property
    def patches(self) -> bool:
        """Whether the ground varies along the path."""
        return self.patch_m > 0

    @property
    def sloped(self) -> bool:
        """Whether gravity is tilted under the floor in some episodes."""
        return self.slope_deg[1] > 0

    @property
    def rough(self) -> bool:
        """Whether the robot walks on rough ground (a heightfield) instead of the flat floor."""
        return self.rough_m[1] > 0


def stochastic(r: Randomization) -> Randomization:
    """``r`` with a contact residual that is stochastic given the state: ground patches of 0.3 m
    whose friction (x0.3-1.5, so feet slip on some) and softness (x0.5-3) vary per patch, three
    pushes per episode instead of one, and rough ground (bumps of 0-3 cm amplitude and
    0.2-0.5 m length scale, drawn per episode). The per-episode ranges of ``r`` stay."""
    return dataclasses.replace(r, pushes=max(r.pushes, 3), patch_m=0.3,
                               patch_friction=(0.3, 1.5), patch_softness=(0.5, 3.0),
                               rough_m=(0.0, 0.03), rough_scale_m=(0.2, 0.5))


@dataclasses.dataclass(frozen=True)
class Robot:
    """A robot definition.

    Attributes:
      name: registry name (``pendulum``, ``pendulum_bouncing``, ``go1``, ``g1``).
      source: where the model comes from, for humans and dataset metadata.
      load_spec: returns the parsed, unedited ``mujoco.MjSpec``.
      edit_spec: makes the spec MJX-ready in place (cone, contact set, solver, timestep).
      joints: actuated joint names, in actuator order.
      feet: contact end-effectors (empty for the pendulum).
      base_body: name of the floating base body (the moving body for fixed-base robots).
      floating_base: whether the first joint is a free joint.
      ctrl_dt: control period (s); an integer multiple of the simulation timestep.
      home_key: keyframe holding the nominal pose, or None for qpos0.
      kp, kd: PD gains of the position servos (N m/rad, N m s/rad), or None for torque control.
      explorer: the data-collecting controller.
      randomization: hidden per-episode randomisation.
      episode_s: default episode length (s).
      min_base_height: below this base height (m) an episode counts as fallen (floating base).
      max_tilt: above this base tilt from upright (rad) an episode counts as fallen.
    """

    name: str
    source: str
    load_spec: Callable[[], mujoco.MjSpec]
    edit_spec: Callable[[mujoco.MjSpec], None]
    joints: tuple[str, ...]
    feet: tuple[Foot, ...]
    base_body: str
    floating_base: bool
    ctrl_dt: float
    home_key: str | None
    kp: tuple[float, ...] | None
    kd: tuple[float, ...] | None
    explorer: Explorer
    randomization: Randomization
    episode_s: float
    min_base_height: float = 0.0
    max_tilt: float = 3.2


def menagerie_spec(robot: str, entry: str, our_name: str) -> mujoco.MjSpec:
    """Parses a MuJoCo Menagerie entry point, with an error that says how to fix a missing model."""
    import mujoco_menagerie

    root = os.environ.get("MENAGERIE_ROOT")
    hint = (f"robot {our_name!r} needs MuJoCo Menagerie's {robot!r} ({entry!r}). Set MENAGERIE_ROOT "
            "to a folder holding it (offline: MENAGERIE_ROOT=../shared/menagerie), or unset it to "
            "let the mujoco-menagerie package download it.")
    try:
        path = mujoco_menagerie.get(robot).xml(entry)
    except mujoco_menagerie.MenagerieError as e:
        raise RobotError(f"{hint} Cause: {e}") from e
    except OSError as e:  # no network, unwritable cache
        raise RobotError(f"{hint} Cause: {e}") from e
    if not path.is_file():
        raise RobotError(f"{hint} Missing file: {path} (MENAGERIE_ROOT={root}).")
    return mujoco.MjSpec.from_file(str(path))


def asset_spec(filename: str) -> mujoco.MjSpec:
    """Parses one of stride_jax's own MJCF files."""
    path = ASSETS / filename
    if not path.is_file():
        raise RobotError(f"stride_jax model file missing: {path} (broken installation?)")
    return mujoco.MjSpec.from_file(str(path))
