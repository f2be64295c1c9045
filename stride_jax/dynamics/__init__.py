"""Dynamics models and their physics: pure functions over params pytrees, jit/vmap-able.

The face of the library (``import stride_jax.dynamics as dyn``)::

    model = dyn.make("stride", spec, act, cfg)          # or: model, params = dyn.load(folder)
    params = model.init(key)
    qdd = dyn.forward_dynamics(model, params, q, qd, tau)
    tau = dyn.inverse_dynamics(model, params, q, qd, qdd)   # M qdd + C qd + g
    M, g = dyn.mass_matrix(model, params, q), dyn.gravity(model, params, q)
    q1, qd1 = model.step(params, q, qd, ctrl, key)           # one control period
    dyn.save(folder, model, params)                           # model.json + params, checksummed

:class:`Model` and :data:`MODELS` (STRIDE, DeLaN, DeLaN's prior alone, LNN + Diffusion, ONN,
Pure Diffusion) are in :mod:`~stride_jax.dynamics.models`; the physics functions in
:mod:`~stride_jax.dynamics.physics`; saving and loading in :mod:`~stride_jax.dynamics.checkpoint`;
training on a robot given as arrays in :func:`stride_jax.train.fit`. ``docs/compose.md`` composes
them into a controller.
"""

from stride_jax.dynamics import (checkpoint, diffusion, flow, generative, lagrangian, mlp, models,
                                 next_obs, physics, stride)
from stride_jax.dynamics.checkpoint import CheckpointError, load, save
from stride_jax.dynamics.integrate import retract, semi_implicit_euler
from stride_jax.dynamics.lagrangian import LNNConfig, lnn_init, lnn_terms
from stride_jax.dynamics.mlp import MLPConfig
from stride_jax.dynamics.models import (DESCRIPTIONS, MODELS, Actuation, Model, make, motors,
                                        spec_from_meta)
from stride_jax.dynamics.physics import (bias_force, coriolis, forward_dynamics, gravity,
                                         inverse_dynamics, kinetic_energy, mass_matrix,
                                         potential_energy)
from stride_jax.dynamics.stride import Scales, StructuredConfig
from stride_jax.types import InputError, ModelSpec

__all__ = ["Actuation", "CheckpointError", "DESCRIPTIONS", "InputError", "LNNConfig",
           "MLPConfig", "MODELS", "Model", "ModelSpec", "Scales", "StructuredConfig",
           "bias_force", "checkpoint", "coriolis", "diffusion", "flow", "forward_dynamics",
           "generative", "gravity", "inverse_dynamics", "kinetic_energy", "lagrangian",
           "lnn_init", "lnn_terms", "load", "make", "mass_matrix", "mlp", "models", "motors",
           "next_obs", "physics", "potential_energy", "retract", "save", "semi_implicit_euler",
           "spec_from_meta", "stride"]
