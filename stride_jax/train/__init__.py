"""Training: the optax loop with resumable orbax checkpoints, the ``stride train`` job, and
:func:`fit` for a robot given as arrays."""

from stride_jax.train.fit import fit

__all__ = ["fit"]
