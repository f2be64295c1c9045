"""Dynamics models and their physics: pure functions over params pytrees, jit/vmap-able."""

from stride_jax.dynamics.integrate import retract, semi_implicit_euler
from stride_jax.dynamics.lagrangian import bias_force, forward_dynamics

__all__ = ["bias_force", "forward_dynamics", "retract", "semi_implicit_euler"]
