"""Control with learned models: the MPPI planner (and, to come, its PPO warm start)."""
