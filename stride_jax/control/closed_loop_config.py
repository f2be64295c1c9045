"""What a closed-loop run does (:mod:`stride_jax.control.closed_loop`): the robot, planner models,
scenarios and MPPI settings, with named presets. Apart from the driver so that the planner's view
of the task (:mod:`stride_jax.control.planning`) can take it without importing the driver.

MPPI's own settings default to :class:`stride_jax.control.mppi.MPPIConfig`'s (one source).
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

from stride_jax.control.mppi import MPPIConfig


@dataclasses.dataclass(frozen=True)
class ClosedLoopConfig:
    """Closed-loop runs.

    Attributes:
      robot: ``go1`` or ``g1`` (the policy and the learned models must be of it).
      models: comma-separated planner models (``oracle``, ``nominal``, ``policy``, ``NAME=RUN``).
      scenarios: comma-separated names of :data:`SCENARIOS`.
      seconds: override every scenario's duration (0: keep).
      mppi: the planner's settings (``--mppi.samples``, ``--mppi.horizon``, ...; the older flat
        flags ``--samples``, ``--horizon``, ``--policy-samples`` ... still answer). Its
        ``noise_std`` is set from ``noise_std`` below (and ``gait_noise``), its
        ``policy_samples`` dropped to 0 without a policy.
      noise_std: exploration std of the joint offsets (rad).
      prior_noise_std: noise std of the policy-prior candidates (``--mppi.prior-fraction``), rad:
        the PPO policy's own action spread (0.079-0.087 rad over its Go1 episodes,
        ``results/planning_diagnosis/``).
      plan_range: bound of the planner's joint offsets around home (rad).
      gait: plan gait parameters jointly with joint residuals (Go1 gait reference).
      gait_noise: exploration std of the gait frequency (Hz); duty 0.15x, offsets 0.25x this.
      policy: PPO run folder supplying candidates (and the ``policy`` model); "" for none.
      learned: learned reward/value file (``reward_value.msgpack``); "" for the analytic cost.
      value_weight: weight of the learned terminal value.
      error_model: a learned one-step error model of the planner's dynamics model
        (``error_model.msgpack`` of :mod:`stride_jax.control.planner_value`), used with
        ``--mppi.error-bound``/``--mppi.error-weight``; "" for none.
      fall_cost: planner cost per step spent fallen (reward units per step).
      track_weight: weight of a quadratic velocity-tracking cost added to the reward terms (per
        (m/s)^2, times dt): the reward's exp-kernels are flat far from the command (at 2 m/s
        below it, exp(-16)), which leaves a planner starting from rest without a direction.
      kernel: how learned structured models run their networks (``xla``; ``pallas`` or
        ``pallas-bf16``: fused kernels on GPUs, ``stride_jax.dynamics.fused``;
        ``pallas-step[-bf16]``: STRIDE's whole step as one kernel where it applies).
      settle_s: tracking errors are counted from this long after each command change (s).
      out: results folder (``closed_loop.json``/``.md`` and plots).
      seed: planner key and terrain seed.
    """

    robot: str = "go1"
    models: str = "oracle,nominal"
    scenarios: str = "step,changes,slope,low_friction,soft,rough"
    seconds: float = 0.0
    mppi: MPPIConfig = MPPIConfig()
    noise_std: float = 0.15
    prior_noise_std: float = 0.08
    plan_range: float = 0.6
    gait: bool = False
    gait_noise: float = 0.2
    policy: str = ""
    learned: str = ""
    value_weight: float = 1.0
    error_model: str = ""
    fall_cost: float = 1.0
    track_weight: float = 1.0
    kernel: str = "xla"
    settle_s: float = 0.5
    out: str = "results/closed_loop"
    seed: int = 0

    # The flat flags of earlier commands (recorded in results/) still answer.
    FLAG_ALIASES: ClassVar[dict[str, str]] = {
        f"mppi.{name}": "--" + name.replace("_", "-")
        for name in ("samples", "horizon", "iterations", "temperature", "smoothing",
                     "policy_samples", "policy_noise", "risk_draws", "risk", "risk_alpha",
                     "risk_weight")}


PRESETS = {
    "tiny": dict(models="oracle", scenarios="step", seconds=0.2,
                 mppi=MPPIConfig(samples=8, horizon=3), settle_s=0.0,
                 out="results/closed_loop_tiny"),
    "default": {},
    "gpu": dict(mppi=MPPIConfig(samples=1024, horizon=20), out="results/closed_loop_gpu"),
}
