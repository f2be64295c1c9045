"""Robot definitions: ``get('go1')`` returns a :class:`Robot`; ``get('path/arm.xml')`` or
``get('path/arm.toml')`` builds one from an MJCF file (:mod:`stride_jax.robots.mjcf`)."""

from stride_jax.robots.base import (Explorer, Foot, ModelInfo, Randomization, Robot, RobotError,
                                    stochastic)
from stride_jax.robots.g1 import G1
from stride_jax.robots.go1 import GO1
from stride_jax.robots.pendulum import PENDULUM, PENDULUM_BOUNCING

ROBOTS: dict[str, Robot] = {r.name: r for r in (PENDULUM, PENDULUM_BOUNCING, GO1, G1)}


def get(name: str) -> Robot:
    """The robot called ``name``, or the one an MJCF / robot file describes (a path ending in
    ``.xml`` or ``.toml``); a clear error listing the known robots otherwise."""
    from stride_jax.robots import mjcf

    if name in ROBOTS:
        return ROBOTS[name]
    if mjcf.is_path(name):
        return mjcf.load(name)
    raise RobotError(f"unknown robot {name!r}; known robots: {', '.join(ROBOTS)}, or an MJCF file "
                     "(.xml) or robot file (.toml)")


__all__ = ["Explorer", "Foot", "ModelInfo", "Randomization", "Robot", "RobotError", "ROBOTS", "get",
           "stochastic"]
