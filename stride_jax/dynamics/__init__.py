"""Dynamics models and their physics: pure functions over params pytrees, jit/vmap-able.

``models`` is the entry point: ``models.make(name, ...)`` or ``models.load(run)`` give a
:class:`~stride_jax.dynamics.models.Model` (STRIDE, DeLaN, LNN + Diffusion, ONN, Pure Diffusion).
"""

from stride_jax.dynamics import (diffusion, flow, generative, lagrangian, mlp, models, next_obs,
                                 stride)
from stride_jax.dynamics.integrate import retract, semi_implicit_euler
from stride_jax.dynamics.lagrangian import (LNNConfig, bias_force, forward_dynamics, lnn_init,
                                            lnn_terms, mass_matrix, potential_energy)

__all__ = ["LNNConfig", "bias_force", "diffusion", "flow", "forward_dynamics", "generative",
           "lagrangian", "lnn_init", "lnn_terms", "mass_matrix", "mlp", "models", "next_obs",
           "potential_energy", "retract", "semi_implicit_euler", "stride"]
