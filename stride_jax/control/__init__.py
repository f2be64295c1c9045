"""Control with learned models: ``mppi`` (the planner), ``planning`` (the planner's view of a
locomotion task), ``episode`` (one closed-loop episode in MJX and its metrics), ``envs`` (MJX
velocity-command environments), ``ppo`` (warm-start policies in resumable chunks), ``learned``
(reward and value models), ``planner_value`` (the value refitted on the planner's rollouts),
``gait``, ``scenarios``. Its jobs (``stride closed-loop``, ``stride ppo``,
``stride fit-reward-value``, ``stride bench-mppi``, the gait study and the Dreamer-MPC ablation)
are in :mod:`stride_jax.jobs`.

Submodules are imported by name (``from stride_jax.control import mppi``), not here: the
environments and PPO pull in Brax, which a planner alone does not need, and eager imports make
``python -m stride_jax.jobs.ppo`` warn about a module imported twice.
"""
