"""The one interface every dynamics model offers, and the registry of models.

A :class:`Model` is a bundle of pure functions over a params pytree (written for one example;
batch with ``vmap``):

* ``init(key) -> params``
* ``loss(params, example, key) -> (scalar, parts)``: ``example`` holds ``q, qd, tau, qdd``
* ``acceleration(params, q, qd, tau, key) -> qdd``: structured models only
* ``step(params, q, qd, ctrl, key) -> (q', qd')``: one control period from a command, with the
  robot's servo model turning commands into joint torques at every substep, as the simulator does
* ``rollout(params, q, qd, ctrls [H, nu], key) -> (qs [H, nq], qds [H, nv])``

The training loop, the evaluation, the MPPI planner and a user's controller all use these.
"""

from __future__ import annotations

import dataclasses
import json
import pathlib
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from stride_jax.dynamics import integrate, mlp, onn, stride
from stride_jax.types import ModelSpec


@dataclasses.dataclass(frozen=True)
class Actuation:
    """How commands become generalised forces (read from a dataset's ``meta.json``).

    Position servos: ``tau_j = clip(kp (ctrl - q_j) - kd qd_j, -fmax, fmax)``; motors (``kp`` is
    None): ``tau_j = ctrl``. ``dof`` maps each actuator to the dof it drives.
    """

    dof: tuple[int, ...]
    kp: tuple[float, ...] | None
    kd: tuple[float, ...] | None
    force_range: tuple[tuple[float, float], ...]
    dt: float  # simulation timestep (s)
    n_substeps: int

    @classmethod
    def from_meta(cls, meta: dict) -> "Actuation":
        return cls(dof=tuple(meta["act_dof"]), kp=_tuple(meta["kp"]), kd=_tuple(meta["kd"]),
                   force_range=tuple(tuple(r) for r in meta["actuator_force_range"]),
                   dt=meta["sim_dt"], n_substeps=meta["n_substeps"])

    def torque(self, q: jax.Array, qd: jax.Array, ctrl: jax.Array, spec: ModelSpec) -> jax.Array:
        """Generalised actuator force ``[nv]`` for command ``ctrl`` ``[nu]`` at state (q, qd)."""
        dof = np.asarray(self.dof)
        if self.kp is None:
            force = ctrl
        else:
            qpos_idx = dof + (1 if spec.floating_base else 0)  # free joint: nq = nv + 1
            force = (jnp.asarray(self.kp) * (ctrl - q[qpos_idx])
                     - jnp.asarray(self.kd) * qd[dof])
        lo, hi = np.asarray(self.force_range).T
        limited = hi > lo  # MuJoCo: an empty range means unlimited
        force = jnp.where(limited, jnp.clip(force, lo, hi), force)
        return jnp.zeros(spec.nv, force.dtype).at[dof].set(force)


def _tuple(x):
    return None if x is None else tuple(x)


class Model(NamedTuple):
    name: str
    stochastic: bool
    init: Callable
    loss: Callable
    acceleration: Callable | None
    step: Callable
    rollout: Callable


def structured(name: str, spec: ModelSpec, act: Actuation, cfg: stride.StructuredConfig,
               scales: stride.Scales = stride.Scales()) -> Model:
    """STRIDE (``name='stride'``, flow residual) or DeLaN (``'delan'``, MLP residual)."""
    stochastic = name == "stride"

    def init(key):
        return stride.init(key, spec, cfg, stochastic)

    def loss(params, ex, key):
        return stride.loss(params, spec, cfg, stochastic, ex["q"], ex["qd"], ex["tau"], ex["qdd"],
                           key, scales)

    def acceleration(params, q, qd, tau, key, nfe=None):
        return stride.acceleration(params, spec, cfg, stochastic, q, qd, tau, key, nfe, scales)[0]

    def step(params, q, qd, ctrl, key, nfe=None):
        def substep(carry, k):
            q, qd = carry
            qdd = acceleration(params, q, qd, act.torque(q, qd, ctrl, spec), k, nfe)
            return integrate.semi_implicit_euler(q, qd, qdd, act.dt, spec.floating_base), None

        (q, qd), _ = jax.lax.scan(substep, (q, qd), jax.random.split(key, act.n_substeps))
        return q, qd

    def rollout(params, q, qd, ctrls, key, nfe=None):
        def body(carry, inp):
            ctrl, k = inp
            nxt = step(params, *carry, ctrl, k, nfe)
            return nxt, nxt

        _, (qs, qds) = jax.lax.scan(body, (q, qd), (ctrls, jax.random.split(key, len(ctrls))))
        return qs, qds

    return Model(name, stochastic, init, loss, acceleration, step, rollout)


def next_observation(spec: ModelSpec, act: Actuation, cfg: stride.StructuredConfig,
                     scales: stride.Scales = stride.Scales()) -> Model:
    """ONN: an MLP from (observation, command) to the next observation, same size as the rest."""
    nu = len(act.dof)

    def step(params, q, qd, ctrl, key=None, nfe=None):
        return onn.step(params, spec, cfg.net, scales, q, qd, ctrl)

    def rollout(params, q, qd, ctrls, key=None, nfe=None):
        def body(carry, ctrl):
            nxt = step(params, *carry, ctrl)
            return nxt, nxt

        _, (qs, qds) = jax.lax.scan(body, (q, qd), ctrls)
        return qs, qds

    return Model("onn", False, lambda key: onn.init(key, spec, cfg.net, nu, scales),
                 lambda params, ex, key: onn.loss(params, spec, cfg.net, scales, ex),
                 None, step, rollout)


MODELS = ("stride", "delan", "onn")


def make(name: str, spec: ModelSpec, act: Actuation, cfg: stride.StructuredConfig,
         scales: stride.Scales = stride.Scales()) -> Model:
    """The model called ``name``; a clear error for unknown names."""
    if name not in MODELS:
        raise ValueError(f"unknown model {name!r}; available: {', '.join(MODELS)}")
    if name == "onn":
        return next_observation(spec, act, cfg, scales)
    return structured(name, spec, act, cfg, scales)


def save_definition(run: pathlib.Path, name: str, spec: ModelSpec, act: Actuation,
                    cfg: stride.StructuredConfig, scales: stride.Scales) -> None:
    """Writes ``run/model.json``: everything :func:`load` needs besides the parameters."""
    as_list = lambda x: np.asarray(x, np.float64).reshape(-1).tolist()
    (pathlib.Path(run) / "model.json").write_text(json.dumps({
        "name": name, "spec": dataclasses.asdict(spec), "actuation": dataclasses.asdict(act),
        "config": dataclasses.asdict(cfg),
        "scales": {k: as_list(v) for k, v in scales._asdict().items()}}, indent=1))


def load(run: str | pathlib.Path) -> tuple[Model, dict]:
    """``(model, params)``: the best (lowest validation loss) parameters of a training run."""
    import orbax.checkpoint as ocp

    run = pathlib.Path(run)
    if not (run / "model.json").is_file():
        raise FileNotFoundError(f"{run} is not a training run (no model.json); train one with "
                                "`stride train`")
    d = json.loads((run / "model.json").read_text())
    spec = ModelSpec(**{k: tuple(v) if isinstance(v, list) else v for k, v in d["spec"].items()})
    a = d["actuation"]
    act = Actuation(dof=tuple(a["dof"]), kp=_tuple(a["kp"]), kd=_tuple(a["kd"]),
                    force_range=tuple(tuple(r) for r in a["force_range"]), dt=a["dt"],
                    n_substeps=a["n_substeps"])
    c = d["config"]
    cfg = stride.StructuredConfig(**dict(c, net=mlp.MLPConfig(**c["net"])))
    sc = stride.Scales(**{k: jnp.asarray(v, jnp.float32) for k, v in d["scales"].items()})
    model = make(d["name"], spec, act, cfg, sc)
    mngr = ocp.CheckpointManager((run / "best").absolute())
    step = mngr.latest_step()
    if step is None:
        raise FileNotFoundError(f"{run / 'best'} holds no checkpoint")
    target = model.init(jax.random.key(0))
    return model, mngr.restore(step, args=ocp.args.StandardRestore(target))
