"""Training: the optax loop with resumable orbax checkpoints, and the ``stride train`` job."""
