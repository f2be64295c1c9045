"""The planner's view of a closed-loop task: augmented state, actions to joint targets, cost.

The planner's state is ``(q, command, gait clock, latched gait, disturbance)`` stacked into its
``q`` (the dynamics carry the command and the disturbance unchanged and advance the clock), so
one jitted planner follows command changes. Its action is a joint-target offset from the home
pose (rad); with ``gait`` it is a residual on a gait reference plus the gait parameters
(:mod:`stride_jax.control.gait`), which MPPI optimises jointly. The cost is the environment's
reward terms that a state determines, negated, plus a tracking term and a fall cost; or the
learned reward and value (plus, with ``learned_track_weight``, the same tracking term).

Offset-free planning (``observer_gain``): the disturbance is a constant acceleration of the
floating base (world-frame linear, body-frame angular; ``[6]``) that the planner's model adds at
every step of its rollouts. The closed loop estimates it online from the model's one-step
prediction errors on the real robot (:func:`stride_jax.control.episode.run_episode`): the classic
disturbance observer of offset-free MPC, which lets any model -- learned or the nominal simulator
-- account for what it does not know and that persists (a slope, a payload, a sagging ground).

Its settings are a :class:`PlanningConfig` (the closed-loop job's ``ClosedLoopConfig`` nests one
beside the planner's :class:`~stride_jax.control.mppi.MPPIConfig`); one episode in MJX is
:func:`stride_jax.control.episode.run_episode`.
Used by the closed-loop job, the gait study and the planner's value
(:mod:`stride_jax.control.planner_value`).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from stride_jax.control import envs, gait as gait_lib, mppi
from stride_jax.dynamics.lagrangian import WORLD_DOWN
from stride_jax.sim import model as sim_model, rollout_mjx


# the model-trust gate's trigger on the disturbance observer's estimate ``d [6]`` and the limit
# (``PlanningConfig.trust_component``): the norm of its linear part (squared, as every gated run
# compared it), or its downward entry
TRUST_COMPONENTS = {"norm": lambda d, limit: jnp.sum(d[:3] ** 2) > limit ** 2,
                    "down": lambda d, limit: -d[2] > limit}
# the same readings over recorded estimates ``[..., 6]`` (numpy or jax), for the analyses of
# closed-loop traces (``experiments/trust_gate.py``, ``experiments/observer_marker.py``)
TRUST_READS = {"norm": lambda d: (d[..., :3] ** 2).sum(-1) ** 0.5, "down": lambda d: -d[..., 2]}


@dataclasses.dataclass(frozen=True)
class PlanningConfig:
    """The task side of the planner: its action space, exploration and cost (the closed-loop
    job nests it as ``planning``: ``--planning.noise-std`` ...).

    Attributes:
      noise_std: exploration std of the joint offsets (rad).
      prior_noise_std: noise std of the policy-prior candidates (``--mppi.prior-fraction``), rad:
        the PPO policy's own action spread (0.079-0.087 rad over its Go1 episodes,
        ``results/planning_diagnosis/``).
      plan_range: bound of the planner's joint offsets around home (rad).
      gait: plan gait parameters jointly with joint residuals (Go1 gait reference).
      gait_noise: exploration std of the gait frequency (Hz); duty 0.15x, offsets 0.25x this.
      value_weight: weight of the learned terminal value.
      value_pessimism: with a value ensemble (``planner_value``'s ``--value.ensemble``), the
        terminal value is the members' mean minus this many standard deviations across them
        (0: their mean): pessimism where the members disagree, off the value's data.
      fall_cost: planner cost per step spent fallen (reward units per step).
      track_weight: weight of a quadratic velocity-tracking cost added to the reward terms (per
        (m/s)^2, times dt): the reward's exp-kernels are flat far from the command (at 2 m/s
        below it, exp(-16)), which leaves a planner starting from rest without a direction.
      learned_track_weight: the same tracking term added to the learned reward (0: the learned
        reward alone, the trade-off the policy was trained on; > 0: the planner's task weighs
        tracking above the reward's smoothness and effort terms).
      observer_gain: gain of the online disturbance observer (per control step; 0: off). Each
        step the estimate moves by this fraction of the base's one-step acceleration error
        (observed minus predicted by the planner's model with the current estimate).
      observer_limit: bound of each disturbance entry (m/s^2, rad/s^2).
      velocity_filter: the learned model as a state estimator's process model (0: off; below
        1): the base's linear velocity the controller (policy and planner) acts on each period
        is ``measured + velocity_filter * (predicted - measured)``, the prediction being the
        observer's (the planner's model from the last period's filtered state, action and
        disturbance estimate, its residual's central sample or one draw as the observer's): a
        steady-state Kalman filter of one gain, for a base-velocity estimate noisier than the
        model's one-period error. The base's alone: the learned models predict the joints'
        velocities a period ahead worse than a robot's encoders measure them (session 81,
        ``results/closed_loop/sensor_noise_go1_cpu/``: all velocities blended at 0.75 doubled
        the tracking error). Needs ``observer_gain`` > 0 and a floating base.
      observer_angular: estimate the base's angular acceleration too (default: the linear
        part only; the angular one-step errors of the learned models are dominated by contact
        transients, not by what persists).
      velocity_integral: integral action on the velocity error (1/s; 0: off): the command
        the planner tracks becomes ``command - velocity_integral * integral(v - command) dt``
        (forward and lateral, base frame; against the governed command where the closed loop
        governs it), integrated from ``velocity_integral_settle_s`` after each command change
        and reset at it, the shift bounded by ``velocity_integral_limit`` (m/s). Why: on Go1's
        slope the learned models' planners walk a steady +0.05 m/s past the command that the
        disturbance observer (a constant base acceleration) does not take out, and the trained
        models rank by that overshoot (``results/planning_diagnosis/README.md``, session 66).
        The scored error stays against the true command.
      velocity_integral_limit: bound of the command shift (m/s).
      velocity_integral_settle_s: how long after a command change the integral waits (s; the
        closed loop's scoring settles as long by default).
      velocity_integral_band: conditional integration (m/s; 0: off): a period's error enters
        the integral only where it is within this band (forward and lateral each), so that a
        transient -- the start-up's acceleration, a push -- does not wind the shift up (the
        textbook anti-windup; not measured in closed loop on the push). It does not make the integral safe where the robot cannot walk
        the command: on G1's 15 degree tilt the integral (band off) wound +0.13 m/s up in the
        first second's acceleration, the planner and the policy it hands to walked 1.0-1.3 m/s
        where they walk 0.85 without, and every episode of every kind fell (24 of 24; 2 of 24
        without); with a 0.1 m/s band it wound up later, once the robot came within the band,
        and the episode still fell (one ONN episode on CPU; ``results/closed_loop_g1_gpu/
        README.md``, session 69). An integral asks for the command; what the robot can do on
        the ground it stands on is another matter, which it does not know.
      overspeed_gain: an overspeed guard (1/s; 0: off), the one-sided counterpart of the
        integral: the speed along the command's direction past the command by more than
        ``overspeed_margin`` (m/s) is integrated, and the controller acting -- the planner, the
        policy it hands the robot to, or the policy alone -- is asked for the command's speed
        less ``overspeed_gain`` times that integral, never more than ``overspeed_limit`` (m/s)
        less and never past a stop; below the command plus the margin the integral drains at
        the shortfall, and it never asks for more than the command. Why: G1's fallback policy
        creeps past its command on the 15 degree tilt given time (past it from 6.3-7.5 s in 3 of
        9 CPU draws, one fell), and a planner's handover brings the creep forward (the down
        gate's 8 s CPU probe: 4 of 4 fell at 6.3-7.5 s with the policy acting;
        ``results/closed_loop/g1_gate_down_cpu/``, session 90). Measured, it is not the fix:
        around the policy alone on that 8 s tilt it lost 1 of 9 draws at gain 2 and 3 of 9 at
        0.5 (unguarded: 1 of 9), lowering the speed asked mid-creep does not stop it
        (``results/closed_loop/g1_policy_tilt_cpu/README.md``, session 90). A stop command, or
        a standing one (no direction), is not guarded.
      overspeed_margin: the overspeed (m/s) the guard lets pass.
      overspeed_limit: the most (m/s) the guard takes off the command's speed.
      model_gravity: tell the planner's model the sensed gravity direction (``Aug.gravity``)
        where it takes one: the Lagrangian models turn their potential to it
        (:func:`stride_jax.dynamics.models.takes_gravity`), so that a model trained on level
        ground knows the gravity of a slope emulated by tilting it, as a real robot's world
        frame would be gravity-aligned; the next-observation models cannot be told (they run
        as without) and MJX runs its own model's gravity (the oracle's: the world's; the
        nominal model's: level). Off: every model as trained. Measured (session 47,
        ``results/planning_diagnosis/README.md``): with ``V_net`` trained on level ground it
        makes things worse (the base pitched 20 degrees is outside what ``V_net`` was fitted
        on; STRIDE fell on the Go1 slope); meant for the ``"com"`` potential
        (``LNNConfig.potential``) or models trained over the orientations told.
      family_std: std of the command offsets of the policy family's candidates
        (``--mppi.family-samples``): vx (m/s) and yaw rate (rad/s); vy gets half.
      family_cost_stop: a prior on the family's offsets that acts at a stop command:
        ``family_cost_stop * exp(-|command|^2 / stop_speed^2)`` is added to
        ``MPPIConfig.family_cost`` (``mppi.make``'s ``family_prior``; ``|command|`` over vx, vy
        in m/s and the yaw rate in rad/s). Why: after G1's stop command its planners creep on
        (+0.11-0.24 m/s over the last second, the policy +0.05): through the learned model the
        plain policy is predicted to drift backward at a stop, and an offset asking it to walk
        wins the tracking cost (``results/planning_diagnosis/README.md``, session 51). A
        constant ``--mppi.family-cost 0.3`` halved that creep in closed loop but gave back the
        planner's gains on soft ground and the tilt, where offsets help at speed
        (``results/closed_loop_g1_gpu/family_cost.md``, session 53); this one prices them at a
        stop only. 0: off; needs a policy family.
      stop_speed: the command magnitude below which ``family_cost_stop`` acts (the exp's scale).
      alarm_speed: the recovery alarm (0: off): while the base's velocity-tracking error
        (``sqrt((vx - vx*)^2 + (vy - vy*)^2 + (yaw rate - yaw rate*)^2 / 2)``, the tracking
        term's, in the planner's state) exceeds this (m/s), the planner draws its recovery
        candidates (``MPPIConfig.alarm_noise_std``): a push or a slip has taken the robot
        where the policy-prior candidates are not to be trusted.
      recovery_noise_std: the recovery candidates' exploration std of the joint offsets (rad);
        planned gait parameters' noise scales by the same factor over ``noise_std``.
      alarm_hold_s: the recovery candidates keep planning this long (s) after the alarm last
        held (``MPPIConfig.alarm_hold``; 0: only while it holds).
      trust_limit: the model-trust gate (m/s^2; 0: off; needs the observer and a policy): while
        the norm of the observer's estimate of the base's linear acceleration disturbance
        exceeds this, the policy's own action is applied instead of the plan (the planner keeps
        planning, ``Info.status`` says ``DISTRUSTED``). A model that needs a large constant
        correction to explain the robot's motion is wrong where the robot now is; a slope of
        angle a asks ``g sin a`` of a right model (2.5 m/s^2 at 15 degrees). Measured on G1
        (``results/closed_loop_g1_gpu/README.md``, session 41): every one of 57 falls of the
        learned planners before it was preceded by an estimate above 3.5 (median 0.6 s
        before), which 0.5% of the steps of the 104 episodes that stayed up reached
        (``results/planning_diagnosis/g1_observer_marker.md``); with the gate at 3.5 (held
        1 s) the three trained STRIDE seeds fell in none of 72 draws over six scenarios.
        What it cannot tell apart: a large real disturbance from model error. A right model on
        a slope steeper than ``asin(trust_limit / g)`` (21 degrees at 3.5), under a hard push or
        with a heavy payload needs that much correction too, and the gate hands the robot to
        the policy there as well (under G1's pushes a third of the time). The upward entry
        alone is no better marker (at 2.5 it preceded 35 of the 57 falls); the downward one,
        not read then, marked 7 of the 8 falls under the 2.5 gate in sessions 86-89 (all on
        the tilt), the floor-plane part 1 (``results/planning_diagnosis/README.md``, session
        89). Told the gravity
        (``model_gravity``), a right model needs no slope correction, so the limit need not
        leave room for one: over G1's sloped-data models told the gravity (session 50,
        ``results/planning_diagnosis/g1_observer_marker_sloped.md``, 57 episodes gated at 3.5)
        an estimate above 2.5 preceded all 5 falls by 2.7 s (median; 3.5: 4 of 5, 0.4 s) and
        held on 2.0% of the upright episodes' steps (1.4 points of it on the tilt, where STRIDE's
        and ONN's models are biased, 0.6 under pushes). At 2.5 on new draws (session 51,
        ``results/closed_loop_g1_gpu/gate25.md``) STRIDE fell in none of 18 episodes over six
        scenarios, but the 1 s hold made the policy act on 12-47% of its steps outside soft
        ground (the estimate above 2.5 on 0-10%): the hold, not the limit, sets the share
        (``experiments/observer_marker.py --holds``).
      trust_component: what of the observer's estimate ``trust_limit`` reads: ``norm``, the
        norm of its linear part (every gated run before session 89), or ``down``, its downward
        entry alone (the model predicting the base higher than it goes). Why: under the 2.5
        gate on G1 (sessions 86-89, 396 episodes) the downward entry marked 7 of the 8 falls
        (all on the tilt) with a third of the norm's crossings where the robot stayed up, and
        none under pushes, where the norm crossed in every one of 72 episodes and handed the
        robot over though a right model plans through a push
        (``results/planning_diagnosis/README.md``, session 89; in sample, a lead). Measured on
        the GPU (session 90, every trained seed of STRIDE, ``results/closed_loop_g1_gpu/
        README.md``): it kept the planner under pushes and on rough ground and tracked closer
        there (0.101 -> 0.092, 0.067 -> 0.062 m/s), but 2 of 12 tilt draws fell where the norm
        lost none: not the default.
      latency_s: the planner's computation time per plan (s; 0: none, the world waits for the
        planner, as every closed-loop row before session 79 ran). A planner on a robot cannot
        stop the world: with it, the closed loop replans once every ``ceil(latency_s / dt)``
        control periods (one plan in flight at a time, as one accelerator runs it), each plan
        applies from the period its computation ends, and meanwhile the plan in force plays on
        (the policy acts at once where the trust gate handed it the robot). Set it to the
        planning step's measured time on the target machine (``stride bench-mppi``; Go1 STRIDE
        at K = 1024, H = 20: 27 ms on an H100, so 2 periods of 20 ms).
      latency_compensation: with ``latency_s``, plan from the state the planner's model
        predicts for the period the plan will apply from (the plan in force's actions in
        between, the observer's estimate included, a stochastic residual's central sample),
        the textbook delay compensation; off: from the state measured when the computation
        starts, the plan's first actions then late.
      latency_feedback: with ``latency_s`` and a policy, the policy's feedback around the plan
        between replans: each period applies ``plan[k] + policy(state now) - policy(x_k)``,
        where ``x_k`` is the state the planner's model predicts for that period along the plan
        (a stochastic residual's central sample): the plan's offset from the policy, with the
        policy's own feedback on what the prediction missed, at the control rate and without
        the plan's latency (the policy takes ~1 ms). Off: the plan's actions as planned.
      trust_hold_s: the policy keeps acting this long (s) after the gate last held
        (``MPPIConfig.distrust_hold``; 0: only while it holds).
      trust_delay_s: the gate hands over only once its trigger has held this long (s) without
        a break (``MPPIConfig.distrust_after``, rounded to the planner's periods: control
        periods, or with ``latency_s`` replanning periods; 0: at once). A push
        drives the observer's estimate past ``trust_limit`` for the push's length and a little
        after, though it is a disturbance the observer and a right model plan through, not the
        model error the gate is for: measured on G1's pushes, the oracle handed the robot to
        the policy in each push window and lost 0.013 m/s to the policy's own episode there
        (``results/closed_loop_g1_gpu/push_gate_oracle.md``). A trigger that outlasts the
        delay (a slope, a wrong model) still hands over, that much later: at 0.2 s on G1 it
        gained under pushes for STRIDE (every trained seed) and DeLaN (on average), lost for
        ONN, and one STRIDE tilt draw in 24 fell, its trigger broken into runs shorter than
        the delay until too late (``results/closed_loop_g1_gpu/trust_delay_targets.md``).
      trust_overshoot: a second trigger of the model-trust gate (m/s; 0: off; needs a policy):
        the policy also acts while the base's forward velocity (base frame) exceeds the
        commanded one the planner sees by more than this. A planner that drives the robot
        faster than asked is acting on a model that expects less speed from its action than
        the robot gives. Read off session 44's two G1 low-friction falls (in sample), and
        refuted on new draws (session 45, ``results/closed_loop_g1_gpu/lowf_fall_onset.md``):
        at 0.15 it handed G1 to the policy 0.3-0.5 s before each fall, and 7 of 24 draws fell
        anyway (6 of 24 without it; the policy could not recover the runaway either), while
        upright STRIDE draws and every DeLaN draw (none fell) passed 0.15 too. Kept, off, for
        other robots and scenarios. What it cannot tell apart: a commanded slow-down (the
        robot is faster than the new command until it has braked) and a push from behind;
        there the policy acts too.
    """

    noise_std: float = 0.15
    prior_noise_std: float = 0.08
    plan_range: float = 0.6
    gait: bool = False
    gait_noise: float = 0.2
    value_weight: float = 1.0
    value_pessimism: float = 0.0
    fall_cost: float = 1.0
    track_weight: float = 1.0
    learned_track_weight: float = 0.0
    observer_gain: float = 0.0
    observer_limit: float = 6.0
    observer_angular: bool = False
    velocity_filter: float = 0.0
    velocity_integral: float = 0.0
    velocity_integral_limit: float = 0.2
    velocity_integral_settle_s: float = 0.5
    velocity_integral_band: float = 0.0
    overspeed_gain: float = 0.0
    overspeed_margin: float = 0.1
    overspeed_limit: float = 0.5
    model_gravity: bool = False
    family_std: float = 0.3
    family_cost_stop: float = 0.0
    stop_speed: float = 0.1
    alarm_speed: float = 0.0
    recovery_noise_std: float = 0.5
    alarm_hold_s: float = 0.0
    trust_limit: float = 0.0
    trust_hold_s: float = 0.0
    trust_delay_s: float = 0.0
    trust_overshoot: float = 0.0
    trust_component: str = "norm"
    latency_s: float = 0.0
    latency_compensation: bool = True
    latency_feedback: bool = False

    def __post_init__(self):
        if not self.latency_s >= 0:
            raise ValueError(f"latency_s={self.latency_s} must be >= 0 (s)")
        if self.trust_limit < 0 or self.trust_hold_s < 0 or self.trust_overshoot < 0:
            raise ValueError(f"trust_limit={self.trust_limit}, trust_hold_s="
                             f"{self.trust_hold_s} and trust_overshoot={self.trust_overshoot} "
                             f"must be >= 0")
        if self.trust_component not in TRUST_COMPONENTS:
            raise ValueError(f"trust_component={self.trust_component!r}: one of "
                             f"{', '.join(TRUST_COMPONENTS)}")
        if not self.trust_delay_s >= 0:
            raise ValueError(f"trust_delay_s={self.trust_delay_s} must be >= 0 (s)")
        if self.trust_delay_s and not (self.trust_limit or self.trust_overshoot):
            raise ValueError(f"trust_delay_s={self.trust_delay_s} delays the model-trust gate: "
                             f"it needs trust_limit or trust_overshoot")
        if self.trust_limit and not self.observer_gain:
            raise ValueError(f"trust_limit={self.trust_limit} reads the disturbance observer's "
                             f"estimate: it needs observer_gain > 0")
        if not 0 <= self.velocity_filter < 1:
            raise ValueError(f"velocity_filter={self.velocity_filter} must be in [0, 1) (the "
                             "prediction's share; 0: off)")
        if self.velocity_filter and not self.observer_gain:
            raise ValueError(f"velocity_filter={self.velocity_filter} blends in the disturbance "
                             "observer's prediction: it needs observer_gain > 0")
        if self.family_cost_stop < 0 or not self.stop_speed > 0:
            raise ValueError(f"family_cost_stop={self.family_cost_stop} must be >= 0 and "
                             f"stop_speed={self.stop_speed} > 0")
        if min(self.velocity_integral, self.velocity_integral_limit,
               self.velocity_integral_settle_s, self.velocity_integral_band) < 0:
            raise ValueError(f"velocity_integral={self.velocity_integral}, "
                             f"velocity_integral_limit={self.velocity_integral_limit}, "
                             f"velocity_integral_settle_s={self.velocity_integral_settle_s} and "
                             f"velocity_integral_band={self.velocity_integral_band} "
                             f"must be >= 0")
        if min(self.overspeed_gain, self.overspeed_margin, self.overspeed_limit) < 0:
            raise ValueError(f"overspeed_gain={self.overspeed_gain}, overspeed_margin="
                             f"{self.overspeed_margin} and overspeed_limit="
                             f"{self.overspeed_limit} must be >= 0")
        if self.alarm_hold_s < 0:
            raise ValueError(f"alarm_hold_s={self.alarm_hold_s} must be >= 0")
        if self.alarm_speed < 0 or not self.recovery_noise_std > 0:
            raise ValueError(f"alarm_speed={self.alarm_speed} must be >= 0 and "
                             f"recovery_noise_std={self.recovery_noise_std} > 0")

    @property
    def trust_gated(self) -> bool:
        """Whether the model-trust gate is on (either of its triggers)."""
        return bool(self.trust_limit or self.trust_overshoot)


class Planning(NamedTuple):
    """The planner-side functions of one configuration (all pure, for one world)."""

    dynamics: Callable  # (q_aug, qd, u, key) -> (q_aug', qd')
    cost: Callable  # (q_aug, qd, u, t) -> []
    value: Callable | None  # (q_aug, qd) -> []
    policy: Callable | None  # (q_aug, qd) -> u
    ctrl: Callable  # (q_aug, u) -> joint targets [nu]
    lo: np.ndarray  # [nu_plan]
    hi: np.ndarray
    noise: tuple  # per action entry
    nominal_u: np.ndarray  # [nu_plan] initial plan
    clock_hz: float = 0.0  # the task's gait clock (G1's policy observes it), without planned gaits
    obs: Callable | None = None  # (q_aug, qd) -> the learned reward's and value's observation
    disagreement: Callable | None = None  # (qs [E, nq+17], qds [E, nv]) -> [] m/s, of E draws
    step_error: Callable | None = None  # (q_aug, qd, u) -> [] learned one-step error (m/s)
    reward_action: Callable | None = None  # (q_aug, u) -> the policy's normalised action [nu]
    observer_gain: float = 0.0  # the disturbance observer's gain (0: off)
    observer_limit: float = 6.0  # bound of each disturbance entry
    observer_angular: bool = False  # estimate the angular entries too
    family: Callable | None = None  # (q_aug, qd, z [3]) -> u: the policy given command + z
    alarm: Callable | None = None  # (q_aug, qd) -> bool []: plan the recovery candidates
    recovery_noise: tuple = ()  # per action entry: the recovery candidates' noise std
    alarm_hold: int = 0  # planner steps the recovery candidates stay after the alarm last held
    distrust: Callable | None = None  # (q_aug, qd) -> bool []: the policy acts, not the plan
    distrust_hold: int = 0  # planner steps the policy keeps acting after distrust last held
    family_prior: Callable | None = None  # (q_aug, qd) -> []: the offsets' prior, state-dependent
    velocity_integral: float = 0.0  # integral action on the velocity error (1/s; 0: off)
    velocity_integral_limit: float = 0.2  # bound of the command shift (m/s)
    velocity_integral_settle_s: float = 0.5  # the integral starts this long after a change (s)
    velocity_integral_band: float = 0.0  # errors beyond it (m/s) do not enter it (0: all do)
    latency_steps: int = 0  # control periods per plan's computation (0: the world waits)
    latency_compensation: bool = True  # plan from the model's prediction for when it applies
    latency_feedback: bool = False  # the policy's feedback around the plan between replans
    velocity_filter: float = 0.0  # the observer's prediction's share in the base's velocity
    distrust_after: int = 0  # planner steps in a row distrust must hold before the policy acts
    overspeed_gain: float = 0.0  # the overspeed guard's gain (1/s; 0: off)
    overspeed_margin: float = 0.1  # the overspeed it lets pass (m/s)
    overspeed_limit: float = 0.5  # the most it takes off the command's speed (m/s)


class Aug(NamedTuple):
    """The planner's state beyond the robot's ``q`` (stacked into the planner's ``q``)."""

    q: jax.Array  # [nq]
    command: jax.Array  # [3] (vx m/s, vy m/s, yaw rad/s), carried unchanged by the dynamics
    clock: jax.Array  # [] gait clock (cycles)
    gait: jax.Array  # [6] gait parameters latched at a rollout's first step
    latched: jax.Array  # [] 1 inside a rollout (after its first step), 0 in the real state
    disturbance: jax.Array  # [6] estimated base acceleration the model misses, held constant
    gravity: jax.Array  # [3] the sensed gravity direction (world, unit), held over a rollout


N_DIST = 6
N_AUG = 3 + 1 + gait_lib.N_GAIT + 1 + N_DIST + 3


def augment(q: jax.Array, command: jax.Array, clock: jax.Array | float = 0.0,
            gait: jax.Array | None = None, latched: jax.Array | float = 0.0,
            disturbance: jax.Array | None = None, gravity: jax.Array | None = None) -> jax.Array:
    """``[nq + N_AUG]``: the robot state with the command, clock, latched gait, disturbance and
    sensed gravity direction (default world down: :func:`stride_jax.control.envs.base_signals`)."""
    gait = jnp.zeros(gait_lib.N_GAIT) if gait is None else gait
    disturbance = jnp.zeros(N_DIST, q.dtype) if disturbance is None else disturbance
    gravity = jnp.asarray(WORLD_DOWN if gravity is None else gravity, q.dtype)
    return jnp.concatenate([q, command, jnp.reshape(clock, (1,)), gait,
                            jnp.reshape(jnp.asarray(latched, q.dtype), (1,)), disturbance,
                            gravity])


def split(q_aug: jax.Array, nq: int) -> Aug:
    if q_aug.shape[-1] != nq + N_AUG:
        raise ValueError(f"planner state must have {nq} + {N_AUG} entries, got {q_aug.shape}")
    g0 = nq + 4
    d0 = g0 + gait_lib.N_GAIT + 1
    return Aug(q_aug[:nq], q_aug[nq:nq + 3], q_aug[nq + 3], q_aug[g0:g0 + gait_lib.N_GAIT],
               q_aug[g0 + gait_lib.N_GAIT], q_aug[d0:d0 + N_DIST],
               q_aug[d0 + N_DIST:d0 + N_DIST + 3])


def apply_disturbance(q: jax.Array, qd: jax.Array, disturbance: jax.Array, dt: float):
    """One step's effect of a constant base acceleration ``disturbance`` [6] on the model's next
    state: the base velocities gain ``dt * disturbance``, the base position ``dt^2 *`` its
    linear part (semi-implicit Euler); the orientation's second-order change is left out."""
    qd = qd.at[:N_DIST].add(dt * disturbance)
    return q.at[:3].add(dt * dt * disturbance[:3]), qd


def integrate_velocity_error(planning: Planning, integral, since, command, prev_command,
                             v_base, dt: float):
    """One control period of :class:`PlanningConfig`'s ``velocity_integral``: ``(integral',
    since')`` from this period's ``command`` (against the last one's: a change resets both),
    the time ``since`` the last change and the base's velocity ``v_base`` (base frame) after
    the period; ``integral`` is the forward and lateral velocity error (m/s) integrated over
    time (s), held where the shift it asks would pass the limit; with a band, an axis's error
    beyond it leaves that axis's integral as it is (conditional integration)."""
    changed = jnp.any(command != prev_command)
    integral = jnp.where(changed, 0.0, integral)
    since = jnp.where(changed, 0.0, since) + dt
    error = v_base[:2] - command[:2]
    counts = since > planning.velocity_integral_settle_s
    if planning.velocity_integral_band > 0:
        counts = counts & (jnp.abs(error) <= planning.velocity_integral_band)
    grown = integral + jnp.where(counts, error * dt, 0.0)
    bound = planning.velocity_integral_limit / max(planning.velocity_integral, 1e-9)
    return jnp.clip(grown, -bound, bound), since


def integral_command(planning: Planning, command, integral):
    """The command the planner tracks under ``velocity_integral``: forward and lateral moved
    against the integrated error; the yaw rate as commanded."""
    return command.at[:2].add(-planning.velocity_integral * integral)


def _along_command(command):
    """The command's forward-lateral speed (m/s) and unit direction (zero where it stands)."""
    speed = jnp.linalg.norm(command[:2])
    return speed, jnp.where(speed > 0, command[:2] / jnp.maximum(speed, 1e-9), 0.0)


def integrate_overspeed(planning: Planning, over, command, v_base, dt: float):
    """One control period of :class:`PlanningConfig`'s ``overspeed_gain``: the integral ``over``
    (m) of the base's speed along the command's direction past the command's own speed plus the
    margin, from ``v_base`` (base frame) after the period; it drains where the robot is slower,
    never below 0, and stays where the shift would pass the limit; a stop command leaves it as
    it is (no direction to guard)."""
    speed, along = _along_command(command)
    excess = v_base[:2] @ along - speed - planning.overspeed_margin
    bound = planning.overspeed_limit / max(planning.overspeed_gain, 1e-9)
    return jnp.where(speed > 0, jnp.clip(over + excess * dt, 0.0, bound), over)


def overspeed_command(planning: Planning, command, over):
    """The command the controller acts on under ``overspeed_gain``: its forward-lateral speed
    lowered by ``overspeed_gain * over`` along its own direction (never past a stop); the yaw
    rate as commanded."""
    speed, along = _along_command(command)
    cut = jnp.minimum(planning.overspeed_gain * over, speed)
    return command.at[:2].add(-cut * along)


def update_disturbance(planning: "Planning", q_aug: jax.Array, qd: jax.Array, u: jax.Array,
                       qd_real: jax.Array, dt: float, key: jax.Array | None) -> jax.Array:
    """The disturbance observer's next estimate ``[6]`` after the real step ``(q_aug, qd) --u-->
    qd_real``: the planner's model predicts that step under the current estimate (in ``q_aug``)
    and the estimate moves by ``planning.observer_gain`` times the base's acceleration error,
    bounded by ``planning.observer_limit`` (a non-finite prediction keeps the estimate).
    ``key=None``: a stochastic model predicts with its residual's central sample."""
    return observe_step(planning, q_aug, qd, u, qd_real, dt, key)[0]


def observe_step(planning: "Planning", q_aug: jax.Array, qd: jax.Array, u: jax.Array,
                 qd_real: jax.Array, dt: float, key: jax.Array | None
                 ) -> tuple[jax.Array, jax.Array]:
    """:func:`update_disturbance`'s estimate and the velocities ``[nv]`` the model predicted
    for after the step (before the estimate moved): what ``velocity_filter`` blends in."""
    nq = q_aug.shape[-1] - N_AUG
    dist = split(q_aug, nq).disturbance
    _, qd_pred = planning.dynamics(q_aug, qd, u, key)
    innovation = (qd_real[:N_DIST] - qd_pred[:N_DIST]) / dt
    if not planning.observer_angular:
        innovation = innovation.at[3:].set(0.0)
    new = jnp.clip(dist + planning.observer_gain * innovation, -planning.observer_limit,
                   planning.observer_limit)
    return jnp.where(jnp.all(jnp.isfinite(new)), new, dist), qd_pred


def servo_torque(sm: sim_model.SimModel, q: jax.Array, qd: jax.Array, ctrl: jax.Array):
    """Joint torques ``[nu]`` (N m) of the robot's position servos (as MuJoCo applies them)."""
    kp, kd = jnp.asarray(sm.robot.kp), jnp.asarray(sm.robot.kd)
    lo, hi = np.asarray(sm.mj.actuator_forcerange).T
    tau = kp * (ctrl - q[7:]) - kd * qd[6:]
    return jnp.where(hi > lo, jnp.clip(tau, lo, hi), tau)


def make_planning(cfg: PlanningConfig, env_cfg: envs.EnvConfig, sm: sim_model.SimModel,
                  model_step: Callable, ppo_policy: Callable | None = None,
                  learned_params: tuple | None = None,
                  gait_cfg: gait_lib.GaitConfig = gait_lib.GaitConfig(),
                  error_params: dict | None = None) -> Planning:
    """Planner functions around ``model_step(q, qd, ctrl, key) -> (q', qd')`` (with
    ``cfg.model_gravity``: ``model_step(q, qd, ctrl, key, down=...)``); ``error_params``:
    a learned one-step error model (:mod:`stride_jax.control.planner_value`) of this model."""
    nq, nu = sm.mj.nq, sm.info.nu
    home = jnp.asarray(sm.info.qpos0[7:])
    c_lo, c_hi = jnp.asarray(sm.info.ctrl_lo), jnp.asarray(sm.info.ctrl_hi)
    dt = sm.robot.ctrl_dt
    obs_of = functools.partial(envs.observe, env_cfg, home)
    if cfg.gait and sm.robot.name != "go1":
        raise ValueError("the gait reference is the Go1's: --planning.gait needs robot go1")

    def gait_of(q_aug, u):
        """Gait parameters in force: a rollout's first sample, held (per-rollout sampling)."""
        a = split(q_aug, nq)
        return jnp.where(a.latched > 0, a.gait, u[nu:nu + gait_lib.N_GAIT])

    def ctrl(q_aug, u):
        a = split(q_aug, nq)
        if cfg.gait:
            g = gait_lib.split_action(jnp.concatenate([u[:nu], gait_of(q_aug, u)]), nu)[1]
            target = gait_lib.reference(gait_cfg, g, a.clock, a.command, home) + u[:nu]
        else:
            target = home + u
        return jnp.clip(target, c_lo, c_hi)

    def dynamics(q_aug, qd, u, key):
        a = split(q_aug, nq)
        told = {"down": a.gravity} if cfg.model_gravity else {}
        q2, qd2 = model_step(a.q, qd, ctrl(q_aug, u), key, **told)
        if cfg.observer_gain:  # off: the model's own step, bit for bit
            q2, qd2 = apply_disturbance(q2, qd2, a.disturbance, dt)
        if not cfg.gait:  # the task's clock runs on inside rollouts (the policy candidates see it)
            return augment(q2, a.command, jnp.mod(a.clock + env_cfg.gait_hz * dt, 1.0),
                           disturbance=a.disturbance, gravity=a.gravity), qd2
        g = gait_of(q_aug, u)
        return augment(q2, a.command, jnp.mod(a.clock + g[0] * dt, 1.0), g, 1.0,
                       a.disturbance, a.gravity), qd2

    def track_error(q_aug, qd):  # squared velocity-tracking error (yaw rate at half weight)
        q, command = split(q_aug, nq)[:2]
        v, w, _ = envs.base_signals(q, qd)
        return jnp.sum((command[:2] - v[:2]) ** 2) + 0.5 * (command[2] - w[2]) ** 2

    def analytic_cost(q_aug, qd, u, t):
        a = split(q_aug, nq)
        q, command = a.q, a.command
        fallen = rollout_mjx.fallen(sm, q)
        terms = envs.state_terms(env_cfg, home, q, qd, command,
                                 servo_torque(sm, q, qd, ctrl(q_aug, u)), fallen, a.gravity)
        _, parts = envs.total_reward(env_cfg, terms, dt)
        return (-sum(parts.values()) + cfg.track_weight * dt * track_error(q_aug, qd)
                + cfg.fall_cost * fallen)

    def obs_aug(q_aug, qd):
        a = split(q_aug, nq)
        return obs_of(a.q, qd, a.command, a.clock, a.gravity)

    def reward_action(q_aug, u):  # the learned models score the normalised policy action
        return (ctrl(q_aug, u) - home) / env_cfg.action_scale

    def disagreement(qs, qds):  # the spread of the draws' base linear velocity (m/s)
        return jnp.sqrt(jnp.sum(jnp.var(qds[:, :3], axis=0)))

    from stride_jax.control import learned as learned_lib
    step_error = None
    if error_params is not None:
        def step_error(q_aug, qd, u):
            x = learned_lib.reward_input(obs_aug(q_aug, qd), reward_action(q_aug, u))
            return jnp.maximum(learned_lib.apply(error_params, x), 0.0)

    value = None
    cost = analytic_cost
    if learned_params is not None:
        r_cost, value = learned_lib.planner_terms(*learned_params, obs_aug, cfg.value_weight,
                                                  cfg.value_pessimism)

        def cost(q_aug, qd, u, t):
            q = split(q_aug, nq).q
            return (r_cost(q_aug, qd, reward_action(q_aug, u), t)
                    + cfg.learned_track_weight * dt * track_error(q_aug, qd)
                    + cfg.fall_cost * rollout_mjx.fallen(sm, q))

    policy = family = None
    if ppo_policy is not None and not cfg.gait:
        key0 = jax.random.key(0)

        def family(q_aug, qd, z):  # the policy asked for the command + z (vx, vy, yaw rate)
            a = split(q_aug, nq)
            return env_cfg.action_scale * ppo_policy(
                obs_of(a.q, qd, a.command + z, a.clock, a.gravity), key0)

        def policy(q_aug, qd):
            return family(q_aug, qd, jnp.zeros(3, q_aug.dtype))

    family_prior = None
    if cfg.family_cost_stop:
        if family is None:
            raise ValueError(f"family_cost_stop={cfg.family_cost_stop} prices the policy "
                             f"family's offsets: it needs a PPO policy (and no planned gait)")

        def family_prior(q_aug, qd):  # the offsets' prior at a stop command
            command = split(q_aug, nq).command
            return cfg.family_cost_stop * jnp.exp(-jnp.sum(command ** 2) / cfg.stop_speed ** 2)

    alarm = None
    if cfg.alarm_speed:
        def alarm(q_aug, qd):
            return track_error(q_aug, qd) > cfg.alarm_speed ** 2

    distrust = None
    if cfg.trust_gated:
        if policy is None:
            which = (f"trust_limit={cfg.trust_limit}" if cfg.trust_limit
                     else f"trust_overshoot={cfg.trust_overshoot}")
            raise ValueError(f"{which} hands control to the policy: it needs a PPO policy (and "
                             f"no planned gait)")

        def distrust(q_aug, qd):
            a = split(q_aug, nq)
            out = jnp.zeros((), bool)
            if cfg.trust_limit:
                out |= TRUST_COMPONENTS[cfg.trust_component](a.disturbance, cfg.trust_limit)
            if cfg.trust_overshoot:
                v, _, _ = envs.base_signals(a.q, qd)
                out |= v[0] - a.command[0] > cfg.trust_overshoot
            return out

    if cfg.latency_feedback and policy is None:
        raise ValueError("latency_feedback puts the policy's feedback around the plan: it needs "
                         "a PPO policy (and no planned gait)")
    r = cfg.plan_range
    lo, hi = np.full(nu, -r, np.float32), np.full(nu, r, np.float32)
    noise = (cfg.noise_std,) * nu
    nominal = np.zeros(nu, np.float32)
    if cfg.gait:
        g_lo, g_hi = gait_cfg.bounds()
        lo, hi = np.concatenate([lo, g_lo]), np.concatenate([hi, g_hi])
        noise = noise + (cfg.gait_noise, 0.15 * cfg.gait_noise) + (0.25 * cfg.gait_noise,) * 4
        trot = gait_lib.named("trot")
        with jax.ensure_compile_time_eval():  # a constant, also where this is traced (the job)
            nominal = np.asarray(gait_lib.join_action(jnp.asarray(nominal), trot), np.float32)
    recovery = tuple(n * cfg.recovery_noise_std / cfg.noise_std if cfg.noise_std else
                     cfg.recovery_noise_std for n in noise)
    lat = latency_steps(cfg, sm.robot.ctrl_dt)
    # the alarm's and the gate's holds and the gate's delay count the planner's steps: one per
    # control period, or with latency_s one per replanning period of ``lat`` control periods
    plan_steps = lambda s: int(round(s / (sm.robot.ctrl_dt * max(lat, 1))))  # noqa: E731
    return Planning(dynamics, cost, value, policy, ctrl, lo, hi, noise, nominal,
                    0.0 if cfg.gait else env_cfg.gait_hz, obs_aug, disagreement, step_error,
                    reward_action, cfg.observer_gain, cfg.observer_limit, cfg.observer_angular,
                    family, alarm, recovery,
                    plan_steps(cfg.alarm_hold_s) if alarm else 0, distrust,
                    plan_steps(cfg.trust_hold_s) if distrust else 0,
                    family_prior, cfg.velocity_integral, cfg.velocity_integral_limit,
                    cfg.velocity_integral_settle_s, cfg.velocity_integral_band,
                    lat, cfg.latency_compensation, cfg.latency_feedback, cfg.velocity_filter,
                    plan_steps(cfg.trust_delay_s) if distrust else 0, cfg.overspeed_gain,
                    cfg.overspeed_margin, cfg.overspeed_limit)


def latency_steps(cfg: PlanningConfig, dt: float) -> int:
    """Control periods of ``dt`` (s) that one plan's computation of ``cfg.latency_s`` spans."""
    return int(math.ceil(cfg.latency_s / dt - 1e-9)) if cfg.latency_s > 0 else 0


def mppi_config(mppi_cfg: mppi.MPPIConfig, cfg: PlanningConfig,
                planning: Planning) -> mppi.MPPIConfig:
    """The run's MPPI settings ``mppi_cfg`` with the task's exploration noise per action entry
    and the policy prior's noise, the policy family's command-offset noise, the recovery
    candidates' noise where the task has an alarm (and no policy candidates, prior or family
    without a policy). The alarm's and the trust gate's holds come from ``cfg`` (seconds,
    converted for the robot): a hold set in control steps on ``mppi_cfg`` that differs is an error,
    not silently replaced."""
    for steps, secs, got in (("alarm_hold", "alarm_hold_s", planning.alarm_hold),
                             ("distrust_hold", "trust_hold_s", planning.distrust_hold),
                             ("distrust_after", "trust_delay_s", planning.distrust_after)):
        mine = getattr(mppi_cfg, steps)
        if mine and mine != got:
            raise ValueError(
                f"MPPIConfig.{steps}={mine} control steps, but the planning's {secs}="
                f"{getattr(cfg, secs):g} s gives {got}: set the hold in seconds "
                f"(PlanningConfig.{secs}, --planning.{secs.replace('_', '-')}); "
                f"MPPIConfig.{steps} is for planners built with mppi.make directly")
    nu = len(planning.lo)
    fam_std = (cfg.family_std, 0.5 * cfg.family_std, cfg.family_std)
    return dataclasses.replace(mppi_cfg, noise_std=planning.noise,
                               prior_noise_std=(cfg.prior_noise_std,) * nu,
                               policy_samples=mppi_cfg.policy_samples if planning.policy else 0,
                               prior_fraction=mppi_cfg.prior_fraction if planning.policy else 0.0,
                               family_samples=mppi_cfg.family_samples if planning.family else 0,
                               family_std=fam_std,
                               alarm_noise_std=planning.recovery_noise if planning.alarm else 0.0,
                               alarm_hold=planning.alarm_hold,
                               distrust_hold=planning.distrust_hold,
                               distrust_after=planning.distrust_after)


def make_planner(planning: Planning, mppi_cfg: mppi.MPPIConfig) -> mppi.Planner:
    """MPPI over the planning functions (build outside jit: it checks its bounds)."""
    return mppi.make(mppi_cfg, planning.dynamics, planning.cost, planning.lo, planning.hi,
                     planning.value, planning.policy, disagreement=planning.disagreement,
                     family=planning.family, step_error=planning.step_error,
                     alarm=planning.alarm, distrust=planning.distrust,
                     family_prior=planning.family_prior)
