"""Control with learned models: ``mppi`` (the planner), ``envs`` (MJX velocity-command
environments), ``ppo`` (warm-start policies in resumable chunks), ``learned`` (reward and value
models), ``gait``, ``scenarios`` and ``closed_loop``. Its jobs (``stride bench-mppi``, the gait
study) are in :mod:`stride_jax.jobs`.

Submodules are imported by name (``from stride_jax.control import mppi``), not here: the
environments and PPO pull in Brax, which a planner alone does not need, and eager imports make
``python -m stride_jax.control.ppo`` warn about a module imported twice.
"""
