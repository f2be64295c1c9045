"""Shared contracts: what a dynamics model needs to know about the robot it models."""

from __future__ import annotations

import dataclasses

import numpy as np


class InputError(ValueError):
    """A model or physics function was called with inputs of the wrong shape or with non-finite
    values."""


def check_shape(fn: str, arg: str, x, shape: tuple[int, ...]) -> None:
    """Raises :class:`InputError` naming ``fn`` and ``arg`` unless ``x`` has ``shape`` (checked
    at trace time: free under ``jit``). Core maths take one example; batches go through ``vmap``.
    """
    got = np.shape(x)
    if got != tuple(shape):
        hint = "; vmap over the batch" if len(got) > len(shape) else ""
        raise InputError(f"{fn}: {arg} must have shape {tuple(shape)} (one example{hint}), "
                         f"got {got}")


@dataclasses.dataclass(frozen=True)
class ModelSpec:
    """Static description of a robot's coordinates for a dynamics model.

    Attributes:
      nq: configuration size (a free joint counts 7: position and quaternion).
      nv: velocity size (a free joint counts 6: world linear, body angular).
      floating_base: whether the first joint is a free joint.
      periodic: per hinge coordinate (after the free joint), whether it wraps around (a
        pendulum's angle) and is therefore fed to networks as (sin, cos).
    """

    nq: int
    nv: int
    floating_base: bool
    periodic: tuple[bool, ...] = ()

    def __post_init__(self):
        n_hinge = self.nq - (7 if self.floating_base else 0)
        if self.floating_base and self.nv != self.nq - 1:
            raise ValueError(f"floating base needs nv = nq - 1, got nq={self.nq}, nv={self.nv}")
        if not self.floating_base and self.nv != self.nq:
            raise ValueError(f"fixed base needs nv = nq, got nq={self.nq}, nv={self.nv}")
        if self.periodic and len(self.periodic) != n_hinge:
            raise ValueError(f"periodic has {len(self.periodic)} entries for {n_hinge} hinges")
