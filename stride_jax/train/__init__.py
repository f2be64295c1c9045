"""Training: the optax loop with resumable orbax checkpoints (:mod:`~stride_jax.train.loop`),
a dynamics model trained on a dataset's transitions with it (:mod:`~stride_jax.train.dynamics`),
what a model of a dataset starts from (:mod:`~stride_jax.train.setup`), and :func:`fit` for a
robot given as arrays. The ``stride train`` job is :mod:`stride_jax.jobs.train`."""

from stride_jax.train.fit import fit

__all__ = ["fit"]
