"""Model predictive path integral control (MPPI) over any dynamics model, in pure JAX.

One planning step (Williams et al., 2017; with the TD-MPC / Dreamer-MPC additions of the paper's
Sec. IV-B):

1. warm start: the previous plan shifted by one step (the last action repeated);
2. ``samples`` action sequences = plan + time-correlated Gaussian noise (``smoothing`` is the AR(1)
   coefficient of the noise along the horizon), clipped to the action bounds; the first
   ``policy_samples`` are instead rolled out by a policy (``policy(q, qd) -> action``) inside
   the model, so a trained policy proposes candidates;
3. every sequence is rolled out through ``dynamics(q, qd, action, key) -> (q', qd')`` with its own
   key (a stochastic model draws its residual latents per rollout);
4. cost = sum of ``running_cost(q, qd, action, t)`` - ``terminal_value(q_H, qd_H)``; with
   ``risk_draws`` R > 1 each candidate is rolled out R times under independent keys (a
   stochastic model's residual draws: the paper's stated future work) and its cost is the
   ``risk`` statistic of the R costs: their mean, ``mean + risk_weight * std``, or the
   conditional value at risk ``CVaR_alpha`` (the mean of the worst ``1 - risk_alpha`` fraction);
5. the new plan is the softmax(-cost / temperature)-weighted mean of the sequences (the
   temperature is relative to the cost spread of the batch when ``normalize`` is set, which makes
   one temperature work across tasks); the first action is applied.

Dreamer-MPC switches (issue 19, item 2; each off by default, so the classic planner is
unchanged):

* **policy-prior sampling** (``prior_fraction``): that share of the noise candidates follows the
  policy in closed loop through the model, ``u_t = policy(x_t) + e_t``, with the AR(1) noise at
  ``prior_noise_std`` (the policy's own action spread), the rest stays around the shifted plan;
* **discount** (``discount`` = gamma): the cost is ``sum_t gamma^t c_t - gamma^H V(x_H)``, the
  return a value trained with that gamma estimates (a short horizon then leans on the value);
* **candidates from a family of policies** (``family_samples``): the policy asked for
  something else -- in the closed loop, the PPO policy given the command plus an offset ``z``
  (held over the rollout). The search then runs in the policy's command space, where its
  rollouts stay on the states the model was trained on (the planning diagnosis: a learned
  model's cost bias is ~0 on the policy's candidates, 0.4-2.1 on noise candidates), and can
  ask for more than the command where the robot falls short of it (a slope). The offsets are
  drawn around the last step's weighted mean (kept in :class:`MPPIState`), shrunk by
  ``family_decay``, within ``family_range``; ``family_cost`` is a prior that pulls them back to
  the plain policy;
* **the model's error where the planner goes** (``error_draws``, ``error_bound``,
  ``error_weight``): each rollout step is predicted under ``error_draws`` keys (a stochastic
  model's residual draws); their spread (``disagreement``, or a caller's learned
  ``step_error``) accumulates in quadrature into the rollout's predicted error
  ``e_t = sqrt(sum_{s<=t} sigma_s^2)``. A rollout whose ``e_t`` exceeds ``error_bound`` is cut:
  its costs from step ``t`` on are replaced by the discounted terminal value at the last trusted
  state, ``- gamma^t V(x_t)``; ``error_weight`` adds ``gamma^t error_weight e_(t+1)`` per kept
  step, down-weighting candidates the model is unsure of;
* **recovery candidates on an alarm** (``alarm_noise_std``, with ``make(..., alarm=)``): while
  ``alarm(q, qd)`` holds (in the closed loop: the robot far from its commanded velocity), the
  policy-prior candidates leave the policy and, with the plan's own noise candidates, become the
  plan plus AR(1) noise at ``alarm_noise_std``. Measured on the Go1 pushed sideways at 1.0 m/s
  (``results/closed_loop_go1_gpu/parts/risk_search/``): candidates near the policy track best
  where the policy copes, but every candidate set holding the policy prior fell there, and wide
  open-loop noise without it recovered; the alarm picks the set by the situation, and
  ``alarm_hold`` keeps it that many steps after the alarm last held. Measured over five seeds
  (same README, "Session 36"): switched at an alarm on the tracking error, the wide set never
  recovered from those pushes (0 of 15); planned at every step it did in 9 of 10. The recovery
  is decided by the plan in hand when the push comes, so the alarm is no substitute for the
  wide set where such pushes are expected; where nothing pushes hard it costs no tracking.

``make`` returns ``init`` and ``step``, pure functions of an immutable :class:`MPPIState`; jit
``step`` once per (samples, horizon, model) and call it every control period.

Failing safe: a state with a NaN or inf (a sensor glitch), or a step in which no rollout stays
finite, does not plan. The step then applies the previous plan shifted by one step (the
warm start, finite by construction: no non-finite plan is ever stored; the action bounds' middle
if a caller's initial plan was not finite), keeps that as its plan, and says why in
``Info.status`` (:data:`PLANNED`, :data:`BAD_STATE`, :data:`NO_FINITE_ROLLOUT`). The next valid
state plans as usual. Where the planner has a policy (``make(..., policy=)``) a step with no
finite rollout from a valid state applies the policy's action instead (a model that diverges
everywhere it is asked, e.g. integrated too coarsely, would otherwise hold its last plan's
actions until the robot stands still: measured so on Go1, `docs/control.md`); the status still
says :data:`NO_FINITE_ROLLOUT` and the plan kept is the shifted one.

Handing back to the policy where the model is not to be trusted (``make(..., distrust=)``): while
``distrust(q, qd)`` holds (for ``distrust_after`` steps in a row first, where set), and
``distrust_hold`` steps after it last held, the step still plans
(the plan stays warm for when trust returns) but applies the policy's own action and says so
(:data:`DISTRUSTED`). In the closed loop the predicate reads the disturbance observer's estimate
(a model that needs a large constant correction to explain what the robot does is wrong where
the robot now is) and, optionally, the base's forward overshoot of the command
(:class:`stride_jax.control.planning.PlanningConfig`'s ``trust_limit`` and ``trust_overshoot``).

Several devices: ``make(..., sharding=sample_sharding())`` splits the rollouts over all local
devices. On a CPU this is how a planner uses more than one core: XLA runs one device's small
operations one after another (a model step at K=128 compiles to ~220 of them, each too small to
split; ``experiments/probes/model_step_time.py``), so ``STRIDE_HOST_DEVICES=2`` (two host devices, see
``stride_jax/_env.py``) runs two halves of the samples side by side: the same plan to float
rounding (tested). Measured on a 2-core CPU, Go1 STRIDE 64 x 3 with one network for L and V,
K=128, H=16 (``STRIDE_HOST_DEVICES=1|2 stride bench-mppi --preset target-small --models stride
--shared-lnn --repeats 30``): 21.1 ms on one device, 13.6 ms on two.
"""

from __future__ import annotations

import dataclasses
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import NamedSharding

from stride_jax import distributed
from stride_jax.control.costs import (RISKS, Dynamics, open_loop_cost, risk_cost,  # noqa: F401
                                     velocity_spread, weights)
from stride_jax.dynamics.models import LATENTS, rollout_keys, step_key


@dataclasses.dataclass(frozen=True)
class MPPIConfig:
    """Planner settings.

    Attributes:
      samples: action sequences per step (K).
      horizon: steps per sequence (H).
      temperature: softmax temperature (lambda); relative to the batch's cost spread when
        ``normalize``.
      noise_std: exploration standard deviation, in action units (scalar or per action).
      smoothing: AR(1) correlation of the noise between consecutive steps, in [0, 1).
      policy_samples: sequences proposed by the policy instead of noise (0 without a policy).
      policy_noise: the noise sequences perturb the policy acting in closed loop inside the
        model (``u_t = policy(x_t) + e_t``) instead of the plan: every candidate stays near the
        policy's own states, where a learned value was fitted (a policy prior in the spirit of
        TD-MPC). Needs a policy; the plan then serves only as the weighted mean that is applied.
      iterations: refinement iterations per control step (each re-samples around the new plan).
      normalize: divide costs by their standard deviation before the softmax.
      risk_draws: rollouts per candidate, each under its own key (1: one draw, the classic
        planner). A deterministic model gives R equal costs.
      risk: how a candidate's R costs become one: ``mean``, ``std`` (mean + ``risk_weight`` x
        standard deviation) or ``cvar`` (mean of the worst ``1 - risk_alpha`` fraction, at
        least one draw). Policy candidates (``policy_samples``, ``policy_noise``) act on the
        states of their own draw; the actions of their first draw stand for the candidate.
      risk_alpha: CVaR level in [0, 1): 0 is the mean, 0.9 the worst 10% of draws.
      risk_weight: the standard deviation's weight of ``risk="std"``.
      latents: a stochastic model's latents along a rollout: drawn afresh at every step
        (``step``) or held for the whole rollout (``rollout``,
        :func:`stride_jax.dynamics.models.rollout_keys`): then each of the ``risk_draws`` is
        one consistent world in which what the model does not know (friction, payload)
        persists, and the risk statistic is taken over worlds rather than over per-step noise
        that averages out along the horizon; or not drawn (``central``): the model steps with
        ``key=None``, its residual's central sample, so each candidate's cost is the model's
        most typical outcome rather than one random draw (no sampling noise in the ranking; a
        deterministic model is unchanged). Error draws (``error_draws``) still draw beside it;
        risk draws would all be equal, so ``central`` takes ``risk_draws`` 1.
      prior_fraction: share of the noise candidates (``samples - policy_samples``) drawn around
        the policy's own closed-loop rollout through the model (``u_t = policy(x_t) + e_t``,
        noise at ``prior_noise_std``) instead of around the shifted plan; 0: none. Needs a
        policy. ``policy_noise`` is the older spelling of 1 with ``noise_std`` as the noise.
      prior_noise_std: the policy-prior candidates' noise std, in action units (scalar or per
        action): the policy's own action spread (Go1's PPO policy: 0.08 rad).
      discount: gamma of the running costs and the terminal value, in (0, 1]; 1: undiscounted
        (the classic planner). Set it to the learned value's gamma.
      error_draws: model evaluations per rollout step under independent keys whose spread is
        the step's predicted error (>= 2; 1: none). The rollout continues with the first draw.
      error_bound: a rollout whose accumulated predicted error exceeds this (in the
        ``disagreement``'s units: m/s of base velocity in the closed loop) is cut there, its
        remaining cost replaced by the terminal value; 0: never cut.
      error_weight: cost per unit predicted error per kept step (down-weights rollouts the
        model is unsure of); 0: none.
      family_samples: candidates from ``family(q, qd, z)``, each with one offset ``z`` held
        over its rollout, drawn around the previous step's weighted mean offset with std
        ``family_std``; the first keeps that mean. 0: none. Needs a ``family``.
      family_std: std of each offset entry (scalar or per entry; its length is ``z``'s size).
      family_range: bound of every offset entry.
      family_cost: a prior on the offsets: ``family_cost * sum((z / family_std)^2)`` is added to
        each family candidate's cost (cost units per candidate; 0: none), so an offset must buy
        a predicted gain larger than its distance from the plain policy (the policy's command).
      family_decay: the previous mean offset is shrunk by this factor before the draws (1:
        kept). Below 1 the offset returns to the plain policy unless the costs keep asking for
        it: the weighted mean of draws around the last mean is otherwise a random walk, and an
        offset that served one command (a slope) outlives a change of command.
      alarm_noise_std: the recovery candidates' noise std in action units (scalar or per
        action; 0: no recovery mode). While the ``alarm`` given to :func:`make` holds, the
        policy-prior candidates (``prior_fraction``) are the shifted plan plus noise instead of
        the policy's rollout, and they and the plan's noise candidates draw it at this std.
        Policy and family candidates stay as they are. Needs an ``alarm``.
      alarm_hold: steps (calls of ``step``: control periods, or replanning periods where the
        plan's computation spans several) the recovery candidates keep planning after the alarm
        last held (0: only while it holds): a recovery that has brought the error under the
        alarm's threshold is not handed back to the policy prior at once.
      distrust_hold: steps the policy keeps acting after the ``distrust`` given to
        :func:`make` last held (0: only while it holds).
      distrust_after: steps in a row the ``distrust`` must hold before the policy acts
        (0 or 1: at once). A brief disturbance that trips it for fewer steps (a push, which the
        disturbance observer sees as a large estimate) is planned through; a lasting one (a
        model wrong where the robot now is) still hands over, this many steps late.
      unroll: horizon steps per loop iteration of the rollouts (``True``: the whole horizon,
        no loop, one CUDA graph on a GPU). Measured: Go1 STRIDE, K=1024, H=30 on an H100, 9.0 ms
        unrolled against 9.5 ms looped (within run-to-run noise); on a 2-core CPU no faster,
        and compilation takes ~2.5x longer.
    """

    samples: int = 128
    horizon: int = 16
    temperature: float = 0.1
    noise_std: float | tuple[float, ...] = 0.3
    smoothing: float = 0.5
    policy_samples: int = 0
    policy_noise: bool = False
    iterations: int = 1
    normalize: bool = True
    risk_draws: int = 1
    risk: str = "mean"
    risk_alpha: float = 0.9
    risk_weight: float = 1.0
    latents: str = "step"
    prior_fraction: float = 0.0
    prior_noise_std: float | tuple[float, ...] = 0.08
    discount: float = 1.0
    error_draws: int = 1
    error_bound: float = 0.0
    error_weight: float = 0.0
    family_samples: int = 0
    family_std: float | tuple[float, ...] = 0.3
    family_range: float = 1.0
    family_decay: float = 1.0
    family_cost: float = 0.0
    alarm_noise_std: float | tuple[float, ...] = 0.0
    alarm_hold: int = 0
    distrust_hold: int = 0
    distrust_after: int = 0
    unroll: int | bool = 1

    def __post_init__(self):
        problems = []
        if self.samples < 1:
            problems.append(f"samples={self.samples} must be >= 1")
        if self.horizon < 1:
            problems.append(f"horizon={self.horizon} must be >= 1")
        if not self.temperature > 0:
            problems.append(f"temperature={self.temperature} must be > 0")
        if np.any(np.asarray(self.noise_std) < 0):
            problems.append(f"noise_std={self.noise_std} must be >= 0")
        if not 0 <= self.smoothing < 1:
            problems.append(f"smoothing={self.smoothing} must be in [0, 1)")
        if not 0 <= self.policy_samples <= self.samples:
            problems.append(f"policy_samples={self.policy_samples} must be in [0, samples]")
        if not 0 <= self.family_samples <= self.samples - self.policy_samples:
            problems.append(f"family_samples={self.family_samples} must be in [0, samples - "
                            f"policy_samples]")
        if self.family_cost < 0:
            problems.append(f"family_cost={self.family_cost} must be >= 0")
        if not 0 <= self.family_decay <= 1:
            problems.append(f"family_decay={self.family_decay} must be in [0, 1]")
        if np.any(np.asarray(self.family_std) < 0) or not self.family_range > 0:
            problems.append(f"family_std={self.family_std} must be >= 0 and family_range="
                            f"{self.family_range} > 0")
        if self.iterations < 1:
            problems.append(f"iterations={self.iterations} must be >= 1")
        if self.risk_draws < 1:
            problems.append(f"risk_draws={self.risk_draws} must be >= 1")
        if self.risk not in RISKS:
            problems.append(f"risk={self.risk!r} must be one of {', '.join(RISKS)}")
        if self.latents not in LATENTS:
            problems.append(f"latents={self.latents!r} must be one of {', '.join(LATENTS)}")
        if self.latents == "central" and self.risk_draws > 1:
            problems.append(f"latents='central' is deterministic: its {self.risk_draws} risk "
                            "draws would be equal (use latents 'step' or 'rollout' with risk_draws)")
        if not 0 <= self.risk_alpha < 1:
            problems.append(f"risk_alpha={self.risk_alpha} must be in [0, 1)")
        if not 0 <= self.prior_fraction <= 1:
            problems.append(f"prior_fraction={self.prior_fraction} must be in [0, 1]")
        if self.prior_fraction and self.policy_noise:
            problems.append("policy_noise and prior_fraction are two spellings of the policy "
                            "prior: set one (policy_noise = prior_fraction 1 at noise_std)")
        if np.any(np.asarray(self.prior_noise_std) < 0):
            problems.append(f"prior_noise_std={self.prior_noise_std} must be >= 0")
        if not 0 < self.discount <= 1:
            problems.append(f"discount={self.discount} must be in (0, 1]")
        if self.error_draws < 1:
            problems.append(f"error_draws={self.error_draws} must be >= 1")
        if self.error_bound < 0 or self.error_weight < 0:
            problems.append(f"error_bound={self.error_bound} and error_weight="
                            f"{self.error_weight} must be >= 0")
        if self.alarm_hold < 0:
            problems.append(f"alarm_hold={self.alarm_hold} must be >= 0")
        if self.distrust_hold < 0:
            problems.append(f"distrust_hold={self.distrust_hold} must be >= 0")
        if self.distrust_after < 0:
            problems.append(f"distrust_after={self.distrust_after} must be >= 0")
        if np.any(np.asarray(self.alarm_noise_std) < 0):
            problems.append(f"alarm_noise_std={self.alarm_noise_std} must be >= 0")
        if self.policy_noise and np.any(np.asarray(self.alarm_noise_std) > 0):
            problems.append("alarm_noise_std acts on the prior_fraction spelling of the policy "
                            "prior, not on policy_noise")
        if not isinstance(self.unroll, bool) and self.unroll < 1:
            problems.append(f"unroll={self.unroll} must be >= 1 or True")
        if problems:
            raise ValueError("bad MPPI config: " + "; ".join(problems))


class MPPIState(NamedTuple):
    plan: jax.Array  # [H, nu] the current mean action sequence
    key: jax.Array
    z: jax.Array | None = None  # [nz] the policy family's weighted mean offset (None: no family)
    held: jax.Array | None = None  # [] int32 recovery steps left after the alarm (None: no alarm)
    distrusted: jax.Array | None = None  # [] int32 policy steps left (None: no distrust)
    streak: jax.Array | None = None  # [] int32 steps in a row distrust held (None: no delay)


# Info.status: what the step did (DISTRUSTED: planned, but the policy's action applied).
PLANNED, BAD_STATE, NO_FINITE_ROLLOUT, DISTRUSTED = 0, 1, 2, 3


class Info(NamedTuple):
    costs: jax.Array  # [K] of the last iteration
    weights: jax.Array  # [K]
    best_cost: jax.Array  # []
    plan: jax.Array  # [H, nu] after the update
    status: jax.Array  # [] int32: PLANNED, why the step fell back to the shifted plan, or
    # DISTRUSTED (the policy acted)
    candidates: jax.Array  # [K, H, nu] the action sequences of the last iteration (costs' order)
    error: jax.Array  # [K] predicted model error at the rollout's end or cut (0 if unmeasured)
    kept: jax.Array  # [K] horizon steps each rollout kept before a cut (H: not cut)
    alarm: jax.Array  # [] bool: the recovery candidates planned this step (``alarm_noise_std``)


class Planner(NamedTuple):
    init: Callable  # (key, plan=None) -> MPPIState
    step: Callable  # (state, q, qd) -> (action [nu], state, Info)
    latents: str = "step"  # how its rollouts draw a stochastic model's latents (MPPIConfig's)


def hold(trigger: jax.Array, left: jax.Array, steps: int) -> tuple[jax.Array, jax.Array]:
    """A trigger held ``steps`` control steps after it last fired (the recovery alarm's
    ``alarm_hold``, the trust gate's ``distrust_hold``): ``(active, left')`` from this step's
    ``trigger`` and the steps ``left`` of the hold before it."""
    return trigger | (left > 0), jnp.where(trigger, steps, jnp.maximum(left - 1, 0))


def sample_sharding(devices: list | None = None) -> NamedSharding | None:
    """The samples split over ``devices`` (all local devices; None on one device)."""
    return distributed.split_leading("samples", devices)


def make(cfg: MPPIConfig, dynamics: Dynamics, running_cost: Callable, action_lo, action_hi,
         terminal_value: Callable | None = None, policy: Callable | None = None,
         sharding: NamedSharding | None = None, disagreement: Callable | None = None,
         step_error: Callable | None = None, family: Callable | None = None,
         alarm: Callable | None = None, distrust: Callable | None = None,
         family_prior: Callable | None = None) -> Planner:
    """An MPPI planner for ``dynamics(q, qd, action, key) -> (q', qd')``.

    ``running_cost(q, qd, action, t) -> []`` is the cost of taking ``action`` at ``(q, qd)`` at
    horizon step ``t``; ``terminal_value(q, qd) -> []`` is subtracted at the end of the horizon
    (or at a cut); ``policy(q, qd) -> action`` proposes ``cfg.policy_samples`` sequences and the
    policy-prior candidates. Model parameters are closed over: ``dynamics = partial(model.step,
    params)``. ``sharding`` (of a leading sample axis, :func:`sample_sharding`) spreads the
    rollouts over devices; the plan-noise, policy-prior and policy groups must each split evenly
    over them. The model's predicted error per step: ``disagreement(qs [E, nq], qds [E, nv]) ->
    []`` of ``cfg.error_draws`` draws (default :func:`velocity_spread`), and/or a learned
    ``step_error(q, qd, action) -> []`` (both: added in quadrature). ``family(q, qd, z) ->
    action``: a family of policies indexed by an offset ``z`` (``cfg.family_samples``);
    ``family_prior(q, qd) -> []``: a coefficient of the offsets' prior that depends on the
    state (the command a task carries in it), added to ``cfg.family_cost``.
    ``alarm(q, qd) -> bool []``: when the recovery candidates plan (``cfg.alarm_noise_std``).
    ``distrust(q, qd) -> bool []``: when the policy acts instead of the plan (needs a policy).
    """
    lo, hi = jnp.asarray(action_lo, jnp.float32), jnp.asarray(action_hi, jnp.float32)
    if lo.ndim != 1 or lo.shape != hi.shape:
        raise ValueError(f"action bounds must be two [nu] vectors, got {lo.shape} and {hi.shape}")
    if not bool(jnp.all(hi > lo)):
        raise ValueError("action bounds: every upper bound must exceed its lower bound")
    if cfg.policy_samples and policy is None:
        raise ValueError(f"policy_samples={cfg.policy_samples} needs a policy")
    if cfg.policy_noise and policy is None:
        raise ValueError("policy_noise needs a policy (the noise perturbs its actions)")
    if cfg.prior_fraction and policy is None:
        raise ValueError(f"prior_fraction={cfg.prior_fraction} needs a policy (its candidates "
                         f"follow the policy through the model)")
    if cfg.family_samples and family is None:
        raise ValueError(f"family_samples={cfg.family_samples} needs a family of policies")
    if family_prior is not None and family is None:
        raise ValueError("family_prior prices the family's offsets: it needs a family of policies")
    if distrust is not None and policy is None:
        raise ValueError("distrust needs a policy (it acts while the model is not trusted)")
    if cfg.distrust_after > 1 and distrust is None:
        raise ValueError(f"distrust_after={cfg.distrust_after} delays the trust gate: it needs "
                         f"a distrust predicate")
    delayed = distrust is not None and cfg.distrust_after > 1
    recovery = bool(np.any(np.asarray(cfg.alarm_noise_std) > 0))
    if recovery and alarm is None:
        raise ValueError(f"alarm_noise_std={cfg.alarm_noise_std} needs an alarm (when the "
                         f"recovery candidates plan)")
    E = cfg.error_draws
    measured = E > 1 or step_error is not None
    if (cfg.error_bound > 0 or cfg.error_weight > 0) and not measured:
        raise ValueError("error_bound and error_weight need the model's predicted error: "
                         "error_draws >= 2 (a stochastic model's draws) or a step_error")
    nu, H, K = lo.shape[0], cfg.horizon, cfg.samples
    n_pol, n_fam = cfg.policy_samples, cfg.family_samples
    n_prior = (K - n_pol - n_fam if cfg.policy_noise
               else int(round(cfg.prior_fraction * (K - n_pol - n_fam))))
    n_plan = K - n_pol - n_fam - n_prior
    z_std = jnp.atleast_1d(jnp.asarray(cfg.family_std, jnp.float32))
    if sharding is not None:
        n_dev = sharding.mesh.size
        if n_plan % n_dev or n_prior % n_dev or n_pol % n_dev or n_fam % n_dev:
            raise ValueError(f"samples={K} with policy_samples={n_pol}, family_samples={n_fam} "
                             f"and {n_prior} policy-prior candidates: each group must split "
                             f"evenly over the sharding's {n_dev} devices")
    shard = (lambda x: x) if sharding is None else (
        lambda x: jax.lax.with_sharding_constraint(x, sharding))
    std = jnp.broadcast_to(jnp.asarray(cfg.noise_std, jnp.float32), (nu,))
    prior_std = std if cfg.policy_noise else jnp.broadcast_to(
        jnp.asarray(cfg.prior_noise_std, jnp.float32), (nu,))
    alarm_std = jnp.broadcast_to(jnp.asarray(cfg.alarm_noise_std, jnp.float32), (nu,))
    value = terminal_value or (lambda q, qd: jnp.zeros(()))
    spread = disagreement or velocity_spread
    discounts = jnp.asarray(cfg.discount ** np.arange(H + 1), jnp.float32)  # gamma^t, t <= H
    cut_on, bound = cfg.error_bound > 0, cfg.error_bound
    central = cfg.latents == "central"

    def init(key: jax.Array, plan: jax.Array | None = None) -> MPPIState:
        if plan is None:
            plan = jnp.broadcast_to(0.5 * (lo + hi), (H, nu))
        if plan.shape != (H, nu):
            raise ValueError(f"plan must have shape ({H}, {nu}), got {plan.shape}")
        return MPPIState(jnp.asarray(plan, jnp.float32), key,
                         jnp.zeros(z_std.shape, jnp.float32) if n_fam else None,
                         jnp.zeros((), jnp.int32) if recovery else None,
                         jnp.zeros((), jnp.int32) if distrust is not None else None,
                         jnp.zeros((), jnp.int32) if delayed else None)

    def model_step(q, qd, u, key):
        """``(q', qd', sigma^2)``: the next state and the squared predicted one-step error."""
        if E > 1:
            qs, qds = jax.vmap(lambda k: dynamics(q, qd, u, k))(jax.random.split(key, E))
            q2, qd2, var = qs[0], qds[0], spread(qs, qds) ** 2
            if central:  # the rollout goes on from the central sample; the draws give the spread
                q2, qd2 = dynamics(q, qd, u, None)
        else:
            (q2, qd2), var = dynamics(q, qd, u, step_key(key, cfg.latents)), jnp.zeros(())
        if step_error is not None:
            var = var + step_error(q, qd, u) ** 2
        return q2, qd2, var

    def rollout(q, qd, key, base, closed: bool, z=None, anchor=None, leave=None):
        """``(cost, actions [H, nu], error, kept)`` of one candidate: ``base`` is its action
        sequence (open loop) or the offsets on the policy acting in closed loop (the family's
        member ``z`` when given). With ``anchor`` (a plan [H, nu]) a closed-loop candidate
        leaves the policy where ``leave`` holds: its actions are then ``anchor + base``."""
        act = policy if z is None else (lambda q, qd: family(q, qd, z))

        def body(carry, inp):
            q, qd, cost, err2, alive, err_kept, kept = carry
            t, k, b = inp
            u = jnp.clip(act(q, qd) + b, lo, hi) if closed else b
            if anchor is not None:
                u = jnp.where(leave, jnp.clip(anchor[t] + b, lo, hi), u)
            q2, qd2, var = model_step(q, qd, u, k)
            err2 = err2 + var
            w = discounts[t]
            cut = alive & (jnp.sqrt(err2) > bound) if cut_on else jnp.zeros((), bool)
            stay = alive & ~cut
            step_cost = running_cost(q, qd, u, t)
            if cfg.error_weight:
                step_cost = step_cost + cfg.error_weight * jnp.sqrt(err2)
            cost = cost + jnp.where(stay, w * step_cost, 0.0)
            if cut_on:  # the last trusted state's value stands for the rest of the rollout
                cost = cost - jnp.where(cut, w * value(q, qd), 0.0)
            err_kept = jnp.where(stay, jnp.sqrt(err2), err_kept)
            return (q2, qd2, cost, err2, stay, err_kept, kept + stay), u

        zero = jnp.zeros(())
        init_carry = (q, qd, zero, zero, jnp.ones((), bool), zero, jnp.zeros((), jnp.int32))
        (qH, qdH, cost, _, alive, err, kept), actions = jax.lax.scan(
            body, init_carry, (jnp.arange(H), rollout_keys(key, H, cfg.latents), base),
            unroll=cfg.unroll)
        terminal = discounts[H] * value(qH, qdH)
        cost = cost - (jnp.where(alive, terminal, 0.0) if cut_on else terminal)
        return cost, actions, err, kept

    # AR(1) noise along the horizon, e_0 = w_0, e_t = rho e_(t-1) + sqrt(1 - rho^2) w_t (unit
    # variance at every step), as one matrix product e = A w with A[t, s] = rho^(t-s) c_s: no
    # sequential loop (on a GPU, a loop of H tiny steps costs more than the product).
    rho = cfg.smoothing
    lag = np.arange(H)[:, None] - np.arange(H)[None, :]
    gain = np.where(np.arange(H) == 0, 1.0, np.sqrt(1.0 - rho ** 2))[None, :]
    ar1 = jnp.asarray(np.where(lag >= 0, rho ** np.maximum(lag, 0) * gain, 0.0), jnp.float32)

    def noise(key, scale=std):
        white = jax.random.normal(key, (K, H, nu))
        return jnp.einsum("ts,ksu->ktu", ar1, white) * scale

    R = cfg.risk_draws

    def drawn(closed: bool, **switch):
        """A candidate's ``(cost, actions, error, kept)`` over R draws: the risk statistic of
        the costs, the first draw's actions (an open-loop candidate's are the same in all), the
        mean error and kept steps. ``switch``: :func:`rollout`'s ``anchor`` and ``leave``."""
        one = lambda q, qd, key, base, z=None: rollout(q, qd, key, base, closed, z, **switch)
        if R == 1:
            return one

        def over_draws(q, qd, key, base, z=None):
            costs, actions, err, kept = jax.vmap(lambda k: one(q, qd, k, base, z))(
                jax.random.split(key, R))
            return (risk_cost(costs, cfg.risk, cfg.risk_alpha, cfg.risk_weight), actions[0],
                    jnp.mean(err), jnp.mean(kept.astype(jnp.float32)))
        return over_draws

    open_loop, closed_loop = drawn(False), drawn(True)
    def batch(fn, q, qd, keys, bases, *per_candidate):
        """``fn`` over the candidates (keys, bases and any further per-candidate inputs)."""
        ins = (keys, bases) + per_candidate
        return jax.vmap(fn, in_axes=(None, None) + (0,) * len(ins))(q, qd, *map(shard, ins))

    def iterate(plan, z_mean, q, qd, key, wide):
        key_noise, key_roll, key_pol = jax.random.split(key, 3)
        groups, zs = [], None
        if cfg.policy_noise:  # the older spelling: every noise candidate around the policy
            groups.append(batch(closed_loop, q, qd, jax.random.split(key_roll, n_prior),
                                noise(key_noise)[:n_prior]))
        else:
            if n_plan:
                scale = jnp.where(wide, alarm_std, std) if recovery else std
                candidates = jnp.clip(plan[None] + noise(key_noise, scale), lo, hi)
                groups.append(batch(open_loop, q, qd, jax.random.split(key_roll, n_plan),
                                    candidates[:n_plan]))
            if n_prior:
                key_prior_noise, key_prior = jax.random.split(jax.random.fold_in(key, 7))
                prior = drawn(True, anchor=plan, leave=wide) if recovery else closed_loop
                scale = jnp.where(wide, alarm_std, prior_std) if recovery else prior_std
                groups.append(batch(prior, q, qd, jax.random.split(key_prior, n_prior),
                                    noise(key_prior_noise, scale)[:n_prior]))
        if n_pol:
            groups.append(batch(closed_loop, q, qd, jax.random.split(key_pol, n_pol),
                                jnp.zeros((n_pol, H, nu))))
        if n_fam:  # the family's members around the last mean offset (the first: that mean)
            key_z, key_fam = jax.random.split(jax.random.fold_in(key, 11))
            z_mean = cfg.family_decay * z_mean
            zs = z_mean + z_std * jax.random.normal(key_z, (n_fam,) + z_std.shape)
            zs = jnp.clip(zs.at[0].set(z_mean), -cfg.family_range, cfg.family_range)
            fam = batch(closed_loop, q, qd, jax.random.split(key_fam, n_fam),
                        jnp.zeros((n_fam, H, nu)), zs)
            if cfg.family_cost or family_prior is not None:
                coef = cfg.family_cost + (0.0 if family_prior is None else family_prior(q, qd))
                prior = coef * jnp.sum((zs / jnp.maximum(z_std, 1e-6)) ** 2, axis=1)
                fam = (fam[0] + prior,) + tuple(fam[1:])
            groups.append(fam)
        costs, actions, err, kept = (jnp.concatenate(x) for x in zip(*groups))
        costs = jnp.where(jnp.isfinite(costs), costs, jnp.inf)  # a diverged rollout gets no weight
        finite = jnp.isfinite(costs)
        w = weights(costs, cfg.temperature, cfg.normalize)
        new_plan = jnp.einsum("k,khu->hu", w, actions)
        ok = finite.any() & jnp.all(jnp.isfinite(new_plan))
        status = jnp.where(ok, PLANNED, NO_FINITE_ROLLOUT).astype(jnp.int32)
        new_plan = jnp.where(ok, new_plan, plan)
        if n_fam:  # the family's candidates are the last group: their weighted mean offset
            w_fam = w[K - n_fam:]
            z_new = jnp.einsum("k,kz->z", w_fam, zs) / jnp.maximum(jnp.sum(w_fam), 1e-12)
            z_mean = jnp.where(ok & (jnp.sum(w_fam) > 1e-12), z_new, z_mean)
        return new_plan, z_mean, Info(costs, w, jnp.min(costs), new_plan, status, actions, err,
                                      kept.astype(jnp.float32), wide)

    def step(state: MPPIState, q: jax.Array, qd: jax.Array):
        key, key_step = jax.random.split(state.key)
        plan = jnp.concatenate([state.plan[1:], state.plan[-1:]])  # warm start: shift
        plan = jnp.where(jnp.all(jnp.isfinite(plan)), plan, 0.5 * (lo + hi))
        good_state = jnp.all(jnp.isfinite(q)) & jnp.all(jnp.isfinite(qd))
        # A bad state still runs the (discarded) rollouts: one program, no branch on the device.
        q_in, qd_in = jnp.where(jnp.isfinite(q), q, 0.0), jnp.where(jnp.isfinite(qd), qd, 0.0)
        warm, info = plan, None
        z = z_warm = state.z
        held = state.held
        wide = jnp.zeros((), bool)
        if recovery:  # the alarm now, or a recovery still held since it last rang
            wide, left = hold(jnp.asarray(alarm(q_in, qd_in), bool), held, cfg.alarm_hold)
            held = jnp.where(good_state, left, held)
        for i in range(cfg.iterations):
            plan, z, info = iterate(plan, z, q_in, qd_in, jax.random.fold_in(key_step, i), wide)
        plan = jnp.where(good_state, plan, warm)
        if n_fam:
            z = jnp.where(good_state, z, z_warm)
        status = jnp.where(good_state, info.status, BAD_STATE).astype(jnp.int32)
        u = plan[0]
        if policy is not None:  # no rollout stayed finite from a valid state: the policy acts
            u_pol = jnp.clip(policy(q_in, qd_in), lo, hi)
            pol_ok = jnp.all(jnp.isfinite(u_pol))
            u = jnp.where((status == NO_FINITE_ROLLOUT) & pol_ok, u_pol, u)
        distrusted, streak = state.distrusted, state.streak
        if distrust is not None:  # the model now, or the policy still held since it last failed
            trigger = jnp.asarray(distrust(q_in, qd_in), bool)
            if delayed:  # only once it has held distrust_after steps in a row
                run = jnp.where(trigger, jnp.minimum(streak + 1, cfg.distrust_after), 0)
                trigger = run >= cfg.distrust_after
                streak = jnp.where(good_state, run, streak)
            failing, left = hold(trigger, distrusted, cfg.distrust_hold)
            hand_over = good_state & failing
            distrusted = jnp.where(good_state, left, distrusted)
            u = jnp.where(hand_over & pol_ok, u_pol, u)
            status = jnp.where(hand_over, DISTRUSTED, status).astype(jnp.int32)
        info = info._replace(plan=plan, status=status)
        return u, MPPIState(plan, key, z, held, distrusted, streak), info

    return Planner(init, step, cfg.latents)
