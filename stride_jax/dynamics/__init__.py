"""Dynamics models and their physics: pure functions over params pytrees, jit/vmap-able."""

from stride_jax.dynamics import flow, lagrangian, mlp, stride
from stride_jax.dynamics.integrate import retract, semi_implicit_euler
from stride_jax.dynamics.lagrangian import (LNNConfig, bias_force, forward_dynamics, lnn_init,
                                            lnn_terms, mass_matrix, potential_energy)

__all__ = ["LNNConfig", "bias_force", "flow", "forward_dynamics", "lagrangian", "lnn_init",
           "lnn_terms", "mass_matrix", "mlp", "potential_energy", "retract",
           "semi_implicit_euler", "stride"]
