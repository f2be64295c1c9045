"""Control with learned models: the MPPI planner, its PPO warm start on MJX environments,
learned reward and value models, gait parameters and closed-loop runs."""

from stride_jax.control import (closed_loop, envs, gait, gait_study, learned, mppi,  # noqa: F401
                                ppo, scenarios)
