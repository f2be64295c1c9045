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

``make`` returns ``init`` and ``step``, pure functions of an immutable :class:`MPPIState`; jit
``step`` once per (samples, horizon, model) and call it every control period.

Failing safe: a state with a NaN or inf (a sensor glitch), or a step in which no rollout stays
finite, does not plan. The step then applies the previous plan shifted by one step (the
warm start, finite by construction: no non-finite plan is ever stored; the action bounds' middle
if a caller's initial plan was not finite), keeps that as its plan, and says why in
``Info.status`` (:data:`PLANNED`, :data:`BAD_STATE`, :data:`NO_FINITE_ROLLOUT`). The next valid
state plans as usual.

Several devices: ``make(..., sharding=sample_sharding())`` splits the rollouts over all local
devices. On a CPU this is how a planner uses more than one core: XLA runs one device's small
operations one after another (a model step at K=128 compiles to ~220 of them, each too small to
split; ``experiments/model_step_time.py``), so ``STRIDE_HOST_DEVICES=2`` (two host devices, see
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
from jax.sharding import NamedSharding, PartitionSpec


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
        if self.iterations < 1:
            problems.append(f"iterations={self.iterations} must be >= 1")
        if self.risk_draws < 1:
            problems.append(f"risk_draws={self.risk_draws} must be >= 1")
        if self.risk not in RISKS:
            problems.append(f"risk={self.risk!r} must be one of {', '.join(RISKS)}")
        if not 0 <= self.risk_alpha < 1:
            problems.append(f"risk_alpha={self.risk_alpha} must be in [0, 1)")
        if not isinstance(self.unroll, bool) and self.unroll < 1:
            problems.append(f"unroll={self.unroll} must be >= 1 or True")
        if problems:
            raise ValueError("bad MPPI config: " + "; ".join(problems))


RISKS = ("mean", "std", "cvar")


def risk_cost(costs: jax.Array, risk: str = "mean", alpha: float = 0.9,
              weight: float = 1.0) -> jax.Array:
    """One cost from ``costs`` ``[R]`` of a candidate's draws: the mean, ``mean + weight * std``
    or ``CVaR_alpha`` (the mean of the ``max(1, round((1 - alpha) R))`` largest). A non-finite
    draw makes the candidate's cost non-finite (it gets no weight)."""
    if risk == "mean":
        return jnp.mean(costs)
    if risk == "std":
        return jnp.mean(costs) + weight * jnp.std(costs)
    worst = max(1, int(round((1.0 - alpha) * costs.shape[0])))
    return jnp.mean(jax.lax.top_k(costs, worst)[0])


class MPPIState(NamedTuple):
    plan: jax.Array  # [H, nu] the current mean action sequence
    key: jax.Array


# Info.status: what the step did.
PLANNED, BAD_STATE, NO_FINITE_ROLLOUT = 0, 1, 2


class Info(NamedTuple):
    costs: jax.Array  # [K] of the last iteration
    weights: jax.Array  # [K]
    best_cost: jax.Array  # []
    plan: jax.Array  # [H, nu] after the update
    status: jax.Array  # [] int32: PLANNED, or why the step fell back to the shifted plan
    candidates: jax.Array  # [K, H, nu] the action sequences of the last iteration (costs' order)


class Planner(NamedTuple):
    init: Callable  # (key, plan=None) -> MPPIState
    step: Callable  # (state, q, qd) -> (action [nu], state, Info)


Dynamics = Callable[[jax.Array, jax.Array, jax.Array, jax.Array], tuple[jax.Array, jax.Array]]


def open_loop_cost(dynamics: Dynamics, running_cost: Callable, value: Callable, q: jax.Array,
                   qd: jax.Array, actions: jax.Array, key: jax.Array, unroll: int | bool = 1
                   ) -> tuple[jax.Array, jax.Array, jax.Array]:
    """``(cost [], qs [H, nq], qds [H, nv])`` of the action sequence ``actions`` ``[H, nu]`` from
    ``(q, qd)``: the running costs summed minus the terminal value, and the states it passes
    (each step's own key: a stochastic model draws its residual per step)."""
    H = actions.shape[0]

    def body(carry, inp):
        q, qd, cost = carry
        u, t, k = inp
        q2, qd2 = dynamics(q, qd, u, k)
        return (q2, qd2, cost + running_cost(q, qd, u, t)), (q2, qd2)

    (q, qd, cost), (qs, qds) = jax.lax.scan(body, (q, qd, jnp.zeros(())),
                                            (actions, jnp.arange(H), jax.random.split(key, H)),
                                            unroll=unroll)
    return cost - value(q, qd), qs, qds


def weights(costs: jax.Array, temperature: float, normalize: bool = True) -> jax.Array:
    """MPPI's weights of ``costs`` ``[K]``: ``softmax(-(c - min c) / temperature)``, the shifted
    costs divided by their RMS over the finite ones first when ``normalize``; a non-finite cost
    gets no weight."""
    costs = jnp.where(jnp.isfinite(costs), costs, jnp.inf)
    finite = jnp.isfinite(costs)
    shifted = costs - jnp.min(costs)
    if normalize:
        spread = jnp.sqrt(jnp.sum(jnp.where(finite, shifted, 0.0) ** 2)
                          / jnp.maximum(finite.sum(), 1))
        shifted = shifted / jnp.maximum(spread, 1e-6)
    return jax.nn.softmax(-shifted / temperature)


def sample_sharding() -> NamedSharding | None:
    """The samples split over all local devices (None on one device)."""
    devices = jax.local_devices()
    if len(devices) == 1:
        return None
    return NamedSharding(jax.sharding.Mesh(np.array(devices), ("samples",)),
                         PartitionSpec("samples"))


def make(cfg: MPPIConfig, dynamics: Dynamics, running_cost: Callable, action_lo, action_hi,
         terminal_value: Callable | None = None, policy: Callable | None = None,
         sharding: NamedSharding | None = None) -> Planner:
    """An MPPI planner for ``dynamics(q, qd, action, key) -> (q', qd')``.

    ``running_cost(q, qd, action, t) -> []`` is the cost of taking ``action`` at ``(q, qd)`` at
    horizon step ``t``; ``terminal_value(q, qd) -> []`` is subtracted at the end of the horizon;
    ``policy(q, qd) -> action`` proposes ``cfg.policy_samples`` sequences. Model parameters are
    closed over: ``dynamics = partial(model.step, params)``. ``sharding`` (of a leading sample
    axis, :func:`sample_sharding`) spreads the rollouts over devices; the number of noise and of
    policy samples must each split evenly over them.
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
    nu, H, K = lo.shape[0], cfg.horizon, cfg.samples
    if sharding is not None:
        n_dev = sharding.mesh.size
        if (K - cfg.policy_samples) % n_dev or cfg.policy_samples % n_dev:
            raise ValueError(f"samples={K} with policy_samples={cfg.policy_samples}: both groups "
                             f"must split evenly over the sharding's {n_dev} devices")
    shard = (lambda x: x) if sharding is None else (
        lambda x: jax.lax.with_sharding_constraint(x, sharding))
    std = jnp.broadcast_to(jnp.asarray(cfg.noise_std, jnp.float32), (nu,))
    value = terminal_value or (lambda q, qd: jnp.zeros(()))

    def init(key: jax.Array, plan: jax.Array | None = None) -> MPPIState:
        if plan is None:
            plan = jnp.broadcast_to(0.5 * (lo + hi), (H, nu))
        if plan.shape != (H, nu):
            raise ValueError(f"plan must have shape ({H}, {nu}), got {plan.shape}")
        return MPPIState(jnp.asarray(plan, jnp.float32), key)

    def rollout(q, qd, actions, key):
        """Cost of an open-loop action sequence."""
        return open_loop_cost(dynamics, running_cost, value, q, qd, actions, key,
                              cfg.unroll)[0], actions

    def policy_rollout(q, qd, key, offsets=None):
        """Cost and actions of the policy acting inside the model (plus ``offsets`` [H, nu])."""
        def body(carry, inp):
            q, qd, cost = carry
            t, k, e = inp
            u = jnp.clip(policy(q, qd) + e, lo, hi)
            q2, qd2 = dynamics(q, qd, u, k)
            return (q2, qd2, cost + running_cost(q, qd, u, t)), u

        offsets = jnp.zeros((H, nu)) if offsets is None else offsets
        (q, qd, cost), actions = jax.lax.scan(body, (q, qd, jnp.zeros(())),
                                              (jnp.arange(H), jax.random.split(key, H), offsets),
                                              unroll=cfg.unroll)
        return cost - value(q, qd), actions

    # AR(1) noise along the horizon, e_0 = w_0, e_t = rho e_(t-1) + sqrt(1 - rho^2) w_t (unit
    # variance at every step), as one matrix product e = A w with A[t, s] = rho^(t-s) c_s: no
    # sequential loop (on a GPU, a loop of H tiny steps costs more than the product).
    rho = cfg.smoothing
    lag = np.arange(H)[:, None] - np.arange(H)[None, :]
    gain = np.where(np.arange(H) == 0, 1.0, np.sqrt(1.0 - rho ** 2))[None, :]
    ar1 = jnp.asarray(np.where(lag >= 0, rho ** np.maximum(lag, 0) * gain, 0.0), jnp.float32)

    def noise(key):
        white = jax.random.normal(key, (K, H, nu))
        return jnp.einsum("ts,ksu->ktu", ar1, white) * std

    R = cfg.risk_draws

    def drawn(fn):
        """``fn(q, qd, key, *args) -> (cost, actions)`` over R draws: the risk statistic of the
        costs and the first draw's actions (an open-loop candidate's are the same in all)."""
        if R == 1:
            return fn

        def over_draws(q, qd, key, *args):
            costs, actions = jax.vmap(lambda k: fn(q, qd, k, *args))(jax.random.split(key, R))
            return risk_cost(costs, cfg.risk, cfg.risk_alpha, cfg.risk_weight), actions[0]
        return over_draws

    open_loop = drawn(lambda q, qd, key, actions: rollout(q, qd, actions, key))
    closed_loop = drawn(policy_rollout)

    def iterate(plan, q, qd, key):
        key_noise, key_roll, key_pol = jax.random.split(key, 3)
        n_noise = K - cfg.policy_samples
        if cfg.policy_noise:
            costs, actions = jax.vmap(closed_loop, in_axes=(None, None, 0, 0))(
                q, qd, shard(jax.random.split(key_roll, n_noise)),
                shard(noise(key_noise)[:n_noise]))
        else:
            candidates = jnp.clip(plan[None] + noise(key_noise), lo, hi)
            costs, actions = jax.vmap(open_loop, in_axes=(None, None, 0, 0))(
                q, qd, shard(jax.random.split(key_roll, n_noise)), shard(candidates[:n_noise]))
        if cfg.policy_samples:
            p_costs, p_actions = jax.vmap(closed_loop, in_axes=(None, None, 0))(
                q, qd, shard(jax.random.split(key_pol, cfg.policy_samples)))
            costs = jnp.concatenate([costs, p_costs])
            actions = jnp.concatenate([actions, p_actions])
        costs = jnp.where(jnp.isfinite(costs), costs, jnp.inf)  # a diverged rollout gets no weight
        finite = jnp.isfinite(costs)
        w = weights(costs, cfg.temperature, cfg.normalize)
        new_plan = jnp.einsum("k,khu->hu", w, actions)
        ok = finite.any() & jnp.all(jnp.isfinite(new_plan))
        status = jnp.where(ok, PLANNED, NO_FINITE_ROLLOUT).astype(jnp.int32)
        new_plan = jnp.where(ok, new_plan, plan)
        return new_plan, Info(costs, w, jnp.min(costs), new_plan, status, actions)

    def step(state: MPPIState, q: jax.Array, qd: jax.Array):
        key, key_step = jax.random.split(state.key)
        plan = jnp.concatenate([state.plan[1:], state.plan[-1:]])  # warm start: shift
        plan = jnp.where(jnp.all(jnp.isfinite(plan)), plan, 0.5 * (lo + hi))
        good_state = jnp.all(jnp.isfinite(q)) & jnp.all(jnp.isfinite(qd))
        # A bad state still runs the (discarded) rollouts: one program, no branch on the device.
        q_in, qd_in = jnp.where(jnp.isfinite(q), q, 0.0), jnp.where(jnp.isfinite(qd), qd, 0.0)
        warm, info = plan, None
        for i in range(cfg.iterations):
            plan, info = iterate(plan, q_in, qd_in, jax.random.fold_in(key_step, i))
        plan = jnp.where(good_state, plan, warm)
        status = jnp.where(good_state, info.status, BAD_STATE).astype(jnp.int32)
        info = info._replace(plan=plan, status=status)
        return plan[0], MPPIState(plan, key), info

    return Planner(init, step)
