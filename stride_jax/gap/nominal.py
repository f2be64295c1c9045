"""The nominal model of a diagnosis, and the simulator's own settings as model-form hypotheses.

**Nominal model.** By default the gap tool replays logs in the robot's MJCF *as shipped*: its own
friction cone, impratio, contact set, contact parameters, time step, integrator and solver
(:func:`load`, ``form="shipped"``). The robots' ``edit_spec`` makes MJX-training edits on top (the
Go1: pyramidal cones, feet-only floor contacts, condim 3 at the feet, a 4 ms Euler step without
implicit damping, 15 solver iterations) that CPU MuJoCo does not need and that a real robot does
not share; that form (``form="training"``) is one model-form hypothesis among others.

**Simulator settings** (:class:`Settings`): what a simulator chooses and a physical robot does not
have -- time step, integrator, friction cone, impratio, contact time constant and damping ratio
(solref), contact impedance (solimp: the ``1 - d`` softness and the transition width), contact
margin, which geoms collide (the model's own set, or feet against the floor only), the feet's
contact dimension and the solver's iteration cap. :func:`apply` puts settings on a model: discrete
ones by value, continuous ones relative to the model they are applied to (scales, and a margin
added), so that :data:`Settings()` (every field ``None`` or neutral) is that model bit for bit.
:mod:`stride_jax.gap.calibrate` fits them as nuisance parameters before any physical effect.

Shapes and units: ``timestep`` in s, ``margin`` in m (added to every colliding geom's margin),
scales dimensionless; all other fields are names (``integrator``, ``cone``, ``contacts``) or
integers (``foot_condim``, ``iterations``).
"""

from __future__ import annotations

import copy
import dataclasses
import functools

import mujoco
import numpy as np

from stride_jax.sim.model import SimModel

FORMS = ("shipped", "training")

INTEGRATORS = {
    "euler": (mujoco.mjtIntegrator.mjINT_EULER, False),  # (integrator, implicit damping disabled)
    "euler_nodamp": (mujoco.mjtIntegrator.mjINT_EULER, True),
    "implicitfast": (mujoco.mjtIntegrator.mjINT_IMPLICITFAST, False),
    "implicit": (mujoco.mjtIntegrator.mjINT_IMPLICIT, False),
    "rk4": (mujoco.mjtIntegrator.mjINT_RK4, False),
}
CONES = {"pyramidal": mujoco.mjtCone.mjCONE_PYRAMIDAL, "elliptic": mujoco.mjtCone.mjCONE_ELLIPTIC}
CONTACTS = ("model", "feet_only")
_EULERDAMP = int(mujoco.mjtDisableBit.mjDSBL_EULERDAMP)

# Continuous settings: name -> (lo, hi, log-scaled, neutral value, what it is). Bounds are wide
# enough for the differences between simulators and contact models seen in practice (solref time
# constants of 0.005-0.05 s against the usual 0.02 s, impratio 1-1000).
CONTINUOUS = {
    "solref_timeconst": (0.3, 3.0, True, 1.0, "contact time constant (solref[0]), factor"),
    "solref_dampratio": (0.3, 3.0, True, 1.0, "contact damping ratio (solref[1]), factor"),
    # factors on 1 - d of solimp's d0 and dmax, each from MuJoCo's floor 1e-4 (d is clamped to [1e-4,
    # 0.9999]: a foot with dmax = 1, Menagerie's Go1, can soften; 0 x anything could not): both
    # together (the default: which of the two matters depends on how far contacts sink against
    # solimp's width -- d0 for the Go1's 3 cm, dmax for MuJoCo's default 1 mm, the G1's), or apart
    # (not by default: where feet sink far less than the width, dmax is barely identified and fits
    # noise; measured on the independent Go1 benchmark). The factors multiply.
    "solimp_softness": (0.2, 5.0, True, 1.0, "contact impedance softness 1 - d (solimp d0 and dmax), factor"),
    "solimp_d0": (0.2, 5.0, True, 1.0, "contact impedance softness 1 - d0 (solimp[0]), factor"),
    "solimp_dmax": (0.2, 50.0, True, 1.0, "contact impedance softness 1 - dmax (solimp[1]), factor"),
    "solimp_width": (0.2, 5.0, True, 1.0, "contact impedance transition width (solimp[2]), factor"),
    "margin": (0.0, 0.005, False, 0.0, "contact margin added to every colliding geom, m"),
    "impratio": (0.03, 30.0, True, 1.0, "frictional-to-normal impedance ratio (impratio), factor"),
}


@dataclasses.dataclass(frozen=True)
class Settings:
    """Simulator settings on top of a model (``None``: as the model has it).

    Attributes:
      timestep: simulation step (s); must divide the control period.
      integrator: a key of :data:`INTEGRATORS` (``euler_nodamp``: Euler without implicit damping).
      cone: ``pyramidal`` or ``elliptic``.
      contacts: ``model`` (the model's own collision set) or ``feet_only`` (only the feet touch
        the floor, nothing else collides: the MJX-training edit).
      foot_condim: contact dimension of the feet's geoms (1, 3, 4 or 6).
      iterations: solver iteration cap (and line-search iterations).
      solref_timeconst, solref_dampratio, solimp_softness, solimp_d0, solimp_dmax, solimp_width,
        impratio: factors on the model's values (1: unchanged); margin: added (m). See
        :data:`CONTINUOUS`.
    """

    timestep: float | None = None
    integrator: str | None = None
    cone: str | None = None
    contacts: str | None = None
    foot_condim: int | None = None
    iterations: int | None = None
    solref_timeconst: float = 1.0
    solref_dampratio: float = 1.0
    solimp_softness: float = 1.0
    solimp_d0: float = 1.0
    solimp_dmax: float = 1.0
    solimp_width: float = 1.0
    margin: float = 0.0
    impratio: float = 1.0

    def __post_init__(self):
        if self.integrator is not None and self.integrator not in INTEGRATORS:
            raise ValueError(f"settings: integrator {self.integrator!r} is not one of {', '.join(INTEGRATORS)}")
        if self.cone is not None and self.cone not in CONES:
            raise ValueError(f"settings: cone {self.cone!r} is not one of {', '.join(CONES)}")
        if self.contacts is not None and self.contacts not in CONTACTS:
            raise ValueError(f"settings: contacts {self.contacts!r} is not one of {', '.join(CONTACTS)}")
        if self.foot_condim is not None and self.foot_condim not in (1, 3, 4, 6):
            raise ValueError(f"settings: foot_condim {self.foot_condim} is not 1, 3, 4 or 6")
        if self.timestep is not None and not self.timestep > 0:
            raise ValueError(f"settings: timestep {self.timestep} must be > 0")
        for name, (_, _, log, _, _) in CONTINUOUS.items():
            v = getattr(self, name)
            if not np.isfinite(v) or (log and v <= 0):
                raise ValueError(f"settings: {name} = {v} must be finite" + (" and > 0" if log else ""))

    def changed(self) -> dict:
        """The fields that differ from "as the model has it"."""
        neutral = Settings()
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)
                if getattr(self, f.name) != getattr(neutral, f.name)}


# library effects that overlap the calibrated contact settings -> the setting each one is exactly
# (a factor on it), or None where no setting reproduces it
OVERLAPS: dict[str, str | None] = {"contact_softness": "solref_timeconst", "ground_friction": None}


def overlapping(names) -> list[str]:
    """The effects of ``names`` that overlap the simulator's contact settings."""
    return [n for n in names if n in OVERLAPS]


def fold_into(s: Settings, fold: dict, names: list[str]) -> Settings:
    """Settings ``s`` with the effects of ``fold`` (name -> parameters) that are one of the
    continuous settings ``names`` turned into it (a factor on it, clipped to its range)."""
    for name, p in fold.items():
        setting = OVERLAPS.get(name)
        if setting is None or setting not in names:
            continue
        lo, hi = CONTINUOUS[setting][:2]
        s = dataclasses.replace(s, **{setting: float(np.clip(getattr(s, setting) * float(np.ravel(p)[0]), lo, hi))})
    return s


# ----------------------------------------------------------------------------- loading


def _shipped_edit(robot):
    """The edit that the shipped form keeps: none of the MJX-training edits, but what defines the
    robot (G1: the data-collection servo gains its definition's kp/kd describe)."""
    if robot.name == "go1":
        return lambda spec: None
    if robot.name == "g1":
        from stride_jax.robots import g1

        def edit(spec):
            for act in spec.actuators:
                kp, kd = g1._gains(act.name)
                act.gainprm[0], act.biasprm[1], act.biasprm[2] = kp, -kp, -kd
        return edit
    return robot.edit_spec  # the pendulums, MJCF robot files: their edit defines the robot


def load(name: str, form: str = "shipped") -> SimModel:
    """The nominal model of robot ``name`` (a registered name or an MJCF / robot file): ``shipped``
    (the MJCF's own cone, contacts, time step, integrator and solver) or ``training`` (with the
    robot's MJX-training edits, :func:`stride_jax.sim.model.load`). For robots without such edits
    (the pendulums, MJCF files) both are the same model."""
    from stride_jax.robots import mjcf
    from stride_jax.sim import model

    if form not in FORMS:
        raise ValueError(f"nominal model form {form!r} is not one of {', '.join(FORMS)}")
    if form == "training":
        return model.load(name)
    return _load_shipped(name, mjcf.file_key(name) if mjcf.is_path(name) else "")


@functools.lru_cache(maxsize=None)
def _load_shipped(name: str, key: str) -> SimModel:
    del key  # part of the cache key only
    from stride_jax import robots
    from stride_jax.sim import model

    robot = robots.get(name)
    return model.compile_robot(dataclasses.replace(robot, edit_spec=_shipped_edit(robot)))


def has_training_edit(name: str) -> bool:
    """Whether the robot's MJX-training form differs from its shipped MJCF."""
    return name in ("go1", "g1")


# ----------------------------------------------------------------------------- settings


def _colliding(m: mujoco.MjModel) -> np.ndarray:
    return (m.geom_contype != 0) | (m.geom_conaffinity != 0)


def _foot_geoms(sm: SimModel) -> np.ndarray:
    return sm.foot_geoms[sm.foot_geoms >= 0]


def _floor_geoms(sm: SimModel) -> np.ndarray:
    """Geoms of the world body (the ground) that collide."""
    m = sm.mj
    return np.flatnonzero((m.geom_bodyid == 0) & _colliding(m))


def integrator_name(m: mujoco.MjModel) -> str:
    nodamp = bool(m.opt.disableflags & _EULERDAMP)
    for name, (integ, nd) in INTEGRATORS.items():
        if int(m.opt.integrator) == int(integ) and (nd == nodamp or integ != mujoco.mjtIntegrator.mjINT_EULER):
            return name
    return str(int(m.opt.integrator))


def cone_name(m: mujoco.MjModel) -> str:
    return next(k for k, v in CONES.items() if int(v) == int(m.opt.cone))


def describe(sm: SimModel) -> dict:
    """The model's own values of every setting (what :class:`Settings` fields are relative to)."""
    m = sm.mj
    col = _colliding(m)
    feet = _foot_geoms(sm)
    nonfoot = col.copy()
    nonfoot[feet] = False
    nonfoot[_floor_geoms(sm)] = False
    return {"timestep": float(m.opt.timestep), "integrator": integrator_name(m), "cone": cone_name(m),
            "impratio": float(m.opt.impratio), "iterations": int(m.opt.iterations),
            "contacts": "feet_only" if len(feet) and not nonfoot.any() else "model",
            "colliding_geoms": int(col.sum()),
            "foot_condim": int(m.geom_condim[feet].max()) if len(feet) else None,
            "solref": np.unique(m.geom_solref[col], axis=0).round(6).tolist(),
            "solimp": np.unique(m.geom_solimp[col], axis=0).round(6).tolist(),
            "margin": np.unique(m.geom_margin[col]).round(6).tolist()}


def timesteps(sm: SimModel, lo: float = 0.0009, hi: float = 0.0101) -> list[float]:
    """Time steps in ``[lo, hi]`` s that divide the control period."""
    dt = sm.robot.ctrl_dt
    out = sorted({round(dt / n, 9) for n in range(1, 101) if lo <= dt / n <= hi})
    return out


def apply(sm: SimModel, s: Settings, base: SimModel | None = None) -> SimModel:
    """``sm`` with settings ``s``: a new :class:`SimModel` (its own ``MjModel`` copy; ``n_substeps``
    follows the time step). The collision set ``model`` restores ``base``'s (default: ``sm``'s),
    so that settings found on a feet-only model can return to the shipped contacts."""
    base = base or sm
    m = copy.copy(sm.mj)
    n_sub = sm.n_substeps
    if s.timestep is not None:
        n = sm.robot.ctrl_dt / s.timestep
        if abs(n - round(n)) > 1e-6 or round(n) < 1:
            raise ValueError(f"settings: timestep {s.timestep} does not divide the control period {sm.robot.ctrl_dt}")
        m.opt.timestep, n_sub = s.timestep, int(round(n))
    if s.integrator is not None:
        integ, nodamp = INTEGRATORS[s.integrator]
        m.opt.integrator = integ
        m.opt.disableflags = (m.opt.disableflags | _EULERDAMP) if nodamp else (m.opt.disableflags & ~_EULERDAMP)
    if s.cone is not None:
        m.opt.cone = CONES[s.cone]
    if s.iterations is not None:
        m.opt.iterations = m.opt.ls_iterations = int(s.iterations)
    feet = _foot_geoms(sm)
    if s.contacts == "feet_only" and len(feet):
        floor = _floor_geoms(base)
        m.geom_contype[:], m.geom_conaffinity[:] = 0, 0
        m.geom_contype[floor], m.geom_conaffinity[floor] = 1, 0
        m.geom_contype[feet], m.geom_conaffinity[feet] = 0, 1
    elif s.contacts == "model":
        m.geom_contype[:], m.geom_conaffinity[:] = base.mj.geom_contype, base.mj.geom_conaffinity
        m.geom_condim[:] = base.mj.geom_condim
    if s.foot_condim is not None and len(feet):
        m.geom_condim[feet] = s.foot_condim
    # continuous settings: only where they differ from neutral (so that neutral is bit for bit)
    for solref in (m.geom_solref, m.pair_solref):
        if s.solref_timeconst != 1.0:
            solref[:, 0] *= s.solref_timeconst
        if s.solref_dampratio != 1.0:
            solref[:, 1] *= s.solref_dampratio
    for solimp in (m.geom_solimp, m.pair_solimp):
        for col, f in ((0, s.solimp_softness * s.solimp_d0), (1, s.solimp_softness * s.solimp_dmax)):
            if f != 1.0:
                solimp[:, col] = np.clip(1 - np.maximum(1 - solimp[:, col], 1e-4) * f, 1e-4, 0.9999)
        if s.solimp_width != 1.0:
            solimp[:, 2] *= s.solimp_width
    if s.margin != 0.0:
        m.geom_margin[:] += s.margin
        m.pair_margin[:] += s.margin
    if s.impratio != 1.0:
        m.opt.impratio *= s.impratio
    return dataclasses.replace(sm, mj=m, n_substeps=n_sub)


def training_settings(sm: SimModel, training: SimModel) -> Settings:
    """The MJX-training form expressed as :class:`Settings` on the shipped model ``sm``."""
    d = describe(training)
    return Settings(timestep=d["timestep"], integrator=d["integrator"], cone=d["cone"], contacts=d["contacts"],
                    foot_condim=d["foot_condim"], iterations=d["iterations"])


def summary(s: Settings, sm: SimModel) -> list[str]:
    """One line per changed setting: "cone: elliptic -> pyramidal", "solref_timeconst: x 1.6 (0.02 -> 0.032 s)"."""
    d = describe(sm)
    out = []
    for k, v in s.changed().items():
        if k in ("timestep",):
            out.append(f"time step: {d['timestep'] * 1e3:g} ms -> {v * 1e3:g} ms")
        elif k in ("integrator", "cone", "contacts", "foot_condim", "iterations"):
            if d.get(k) != v:
                out.append(f"{k}: {d.get(k)} -> {v}")
        elif k == "margin":
            out.append(f"contact margin: +{v * 1e3:.2g} mm")
        elif k == "impratio":
            out.append(f"impratio: {d['impratio']:g} -> {d['impratio'] * v:.3g}")
        elif k == "solref_timeconst":
            tc = [r[0] for r in d["solref"]]
            out.append(f"contact time constant (solref): x {v:.3g} ({_rng(tc)} -> {_rng([t * v for t in tc])} s)")
        elif k == "solref_dampratio":
            dr = [r[1] for r in d["solref"]]
            out.append(f"contact damping ratio (solref): x {v:.3g} ({_rng(dr)} -> {_rng([x * v for x in dr])})")
        elif k == "solimp_softness":
            out.append(f"contact impedance softness 1 - d (solimp d0, dmax): x {v:.3g}")
        elif k in ("solimp_d0", "solimp_dmax"):
            out.append(f"contact impedance softness 1 - {k[7:]} (solimp): x {v:.3g}")
        elif k == "solimp_width":
            out.append(f"contact impedance width (solimp): x {v:.3g}")
    return out


def _rng(xs) -> str:
    lo, hi = min(xs), max(xs)
    return f"{lo:.3g}" if abs(hi - lo) <= 1e-12 else f"{lo:.3g}-{hi:.3g}"
