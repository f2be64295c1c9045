"""Robot definitions: ``get('go1')`` returns a :class:`Robot`."""

from stride_jax.robots.base import (Explorer, Foot, ModelInfo, Randomization, Robot, RobotError,
                                    stochastic)
from stride_jax.robots.g1 import G1
from stride_jax.robots.go1 import GO1
from stride_jax.robots.pendulum import PENDULUM, PENDULUM_BOUNCING

ROBOTS: dict[str, Robot] = {r.name: r for r in (PENDULUM, PENDULUM_BOUNCING, GO1, G1)}


def get(name: str) -> Robot:
    """The robot called ``name``; a clear error listing the known robots otherwise."""
    try:
        return ROBOTS[name]
    except KeyError:
        raise RobotError(f"unknown robot {name!r}; known robots: {', '.join(ROBOTS)}") from None


__all__ = ["Explorer", "Foot", "ModelInfo", "Randomization", "Robot", "RobotError", "ROBOTS", "get",
           "stochastic"]
