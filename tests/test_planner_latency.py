"""A planner whose computation takes control periods (``PlanningConfig.latency_s``): it replans
once every ``lat`` periods, each plan applies from the period its computation ends, the plan in
force plays on meanwhile, and with compensation the plan starts from the model's prediction for
when it applies. Driven period by period through ``episode._late_plan`` with a toy model whose
prediction is exact, and once through the closed loop on Go1 (chunks included)."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from mujoco import mjx

from stride_jax.control import envs, mppi
from stride_jax.control import episode as ep
from stride_jax.control import planning as planning_lib
from stride_jax.jobs import closed_loop as cl

NQ, H, DT = 3, 6, 0.02
BIG = 50.0  # the toy's action bounds; its policy asks for more and is clipped to it


def _toy(lat: int, compensate: bool, policy=None, feedback: bool = False, big: float = BIG
         ) -> planning_lib.Planning:
    def dynamics(q_aug, qd, u, key):  # x moves by 1 + u[0] per period: the actions matter
        a = planning_lib.split(q_aug, NQ)
        q2 = a.q.at[0].add(1.0 + u[0])
        return planning_lib.augment(q2, a.command, a.clock, disturbance=a.disturbance,
                                    gravity=a.gravity), qd

    lo, hi = np.full(1, -big, np.float32), np.full(1, big, np.float32)
    if policy is True:  # asks for more than the bounds
        policy = lambda q, qd: jnp.full(1, 99.0)
    return planning_lib.Planning(
        dynamics, None, None, policy, None, lo, hi, (0.1,), np.zeros(1, np.float32),
        latency_steps=lat, latency_compensation=compensate, latency_feedback=feedback)


def _planner(distrust_at: int | None = None) -> mppi.Planner:
    """A planner whose plan's action k is ``1000 * call + 10 * k + x`` where ``x`` is the
    position it planned from (so the test reads which call's plan acts, at which index, from
    which state) and whose ``call`` counts its calls (``MPPIState.held``); its call
    ``distrust_at`` hands the robot to the policy."""
    def init(key, plan=None):
        return mppi.MPPIState(jnp.zeros((H, 1)) if plan is None else plan, key,
                              held=jnp.zeros((), jnp.int32))

    def step(state, q_aug, qd):
        call = state.held
        x = planning_lib.split(q_aug, NQ).q[0]
        plan = (1000.0 * call + 10.0 * jnp.arange(H) + x)[:, None]
        status = jnp.where(call == (-1 if distrust_at is None else distrust_at),
                           mppi.DISTRUSTED, mppi.PLANNED).astype(jnp.int32)
        z = jnp.zeros(1)
        info = mppi.Info(z, z, z[0], plan, status, plan[None], z, jnp.full(1, H, jnp.int32),
                         jnp.zeros((), bool))
        return plan[0], mppi.MPPIState(plan, state.key, held=call + 1), info

    return mppi.Planner(init, step)


def _run(planning, planner, n: int, drift: float = 0.0):
    """``n`` periods of the closed loop's latency logic on a world that moves as the toy model
    plus ``drift`` per period (which the model does not know): the applied actions, the
    positions before each period and the statuses in force."""
    q = jnp.array([0.0, 0.0, 0.0])
    ps = planner.init(jax.random.key(0))
    quiet = (jnp.asarray(mppi.PLANNED, jnp.int32), jnp.zeros(()), jnp.zeros((), bool))
    refs = ((jnp.full((planning.latency_steps, 1), jnp.nan),) * 2
            if planning.latency_feedback else ())
    late = (ps.plan, quiet, quiet, *refs)
    up, dist, cmd = jnp.array([0.0, 0.0, -1.0]), jnp.zeros(planning_lib.N_DIST), jnp.zeros(3)
    applied, xs, statuses = [], [], []
    for t in range(n):
        q_aug = planning_lib.augment(q, cmd, 0.0, disturbance=dist, gravity=up)
        u, ps, late = ep._late_plan(planning, planner, late, ps, jnp.asarray(t),
                                    planning.latency_steps, q_aug, jnp.zeros(2), False, 1, DT)
        applied.append(float(u[0]))
        xs.append(float(q[0]))
        statuses.append(int(late[1][0]))
        q = planning_lib.split(planning.dynamics(q_aug, jnp.zeros(2), u, None)[0], NQ).q
        q = q.at[0].add(drift)
    return np.array(applied), np.array(xs), np.array(statuses)


@pytest.mark.parametrize("lat", [1, 2, 3, H + 2])
def test_each_plan_acts_from_when_its_computation_ends_from_the_state_then(lat):
    """With compensation the plan computed at period ``b`` (call ``b / lat``) acts over periods
    ``b + lat .. b + 2 lat - 1``, from its index 0, and was planned from the position the robot
    then has (the toy's prediction is exact); the first ``lat`` periods play the initial plan.
    Without, the same schedule, planned from the position at ``b``: late by ``lat`` periods. A
    computation longer than the plan (``H + 2``) holds the plan's last action."""
    n = 4 * lat + 1
    for compensate in (True, False):
        u, x, _ = _run(_toy(lat, compensate), _planner(), n)
        np.testing.assert_array_equal(u[:lat], 0.0)  # the initial plan, before any computation
        for t in range(lat, n):
            start = t - t % lat  # the period the plan in force took force
            call, k = start // lat - 1, t - start
            seen = x[start] if compensate else x[start - lat]
            assert u[t] == pytest.approx(1000 * call + 10 * min(k, H - 1) + seen), (compensate, t)


def test_a_plan_in_flight_warm_starts_from_the_plan_in_force_shifted_to_when_it_applies():
    """The planner's warm start (its state's plan, which its own step shifts once more) is the
    plan in force shifted by ``lat - 1``, the last action repeated."""
    lat, seen = 3, []
    base = _planner()

    def step(state, q_aug, qd):
        jax.debug.callback(lambda p: seen.append(np.asarray(p)), state.plan[:, 0])
        return base.step(state, q_aug, qd)

    _run(_toy(lat, True), mppi.Planner(base.init, step), lat + 1)
    np.testing.assert_array_equal(seen[0], 0.0)  # the initial plan
    # call 1 (period 3) starts from call 0's plan, 10 k + x, shifted by 2: 10 [2, 3, 4, 5, 5, 5] + x
    np.testing.assert_allclose(seen[1] - seen[1][0], [0, 10, 20, 30, 30, 30], atol=1e-6)


def test_a_hand_over_lets_the_policy_act_at_once_for_the_plans_window():
    """Where the trust gate handed the robot to the policy in a plan's computation, the policy
    (clipped to the bounds) acts every period of that plan's window, and the window reports
    ``DISTRUSTED``; the windows before and after play their plans."""
    lat = 2
    u, _, status = _run(_toy(lat, True, policy=True), _planner(distrust_at=1), 4 * lat)
    # call 1 is computed at period 2 and in force over periods 4-5
    np.testing.assert_array_equal(status, [0, 0, 0, 0, mppi.DISTRUSTED, mppi.DISTRUSTED, 0, 0])
    np.testing.assert_array_equal(u[4:6], BIG)
    assert (u[:4] < BIG).all() and (u[6:] > 1000 * 2 - 1).all()


def test_the_policys_feedback_corrects_what_the_plans_prediction_missed(go1):
    """With the policy's feedback each period applies ``plan[k] + policy(x now) - policy(x_k)``,
    ``x_k`` the model's prediction along the plan: where the model is exact nothing changes;
    where the world drifts by 0.25 per period (unknown to the model) a policy ``-x`` takes the
    drift off each action, which the plan as planned does not."""
    lat, n, big = 3, 10, 1e9  # bounds that never clip
    policy = lambda q_aug, qd: -planning_lib.split(q_aug, NQ).q[:1]
    plain, _, _ = _run(_toy(lat, True, policy, big=big), _planner(), n)
    fed, _, _ = _run(_toy(lat, True, policy, feedback=True, big=big), _planner(), n)
    np.testing.assert_allclose(fed, plain, atol=1e-2)  # an exact model: x = x_k everywhere
    seen = []  # the positions each call planned from
    base = _planner()

    def step(state, q_aug, qd):
        jax.debug.callback(lambda x: seen.append(float(x)), planning_lib.split(q_aug, NQ).q[0])
        return base.step(state, q_aug, qd)

    u, x, _ = _run(_toy(lat, True, policy, feedback=True, big=big),
                   mppi.Planner(base.init, step), n, drift=0.25)
    for t in range(lat, n):
        start = t - t % lat
        call, k = start // lat - 1, t - start
        plan = 1000 * call + 10 * np.arange(H) + seen[call]
        x_k = seen[call] + sum(1.0 + plan[j] for j in range(k))  # the model's prediction
        assert u[t] == pytest.approx(plan[k] - x[t] + x_k, abs=0.05), t
        assert abs(x[t] - x_k) >= 0.25 - 1e-3  # the prediction missed (the feedback holds the
        # miss to the last period's drift; the plan as planned lets it add up over the window)
    with pytest.raises(ValueError, match="latency_feedback .* needs a PPO policy"):
        planning_lib.make_planning(planning_lib.PlanningConfig(latency_s=0.02,
                                                               latency_feedback=True),
                                   envs.config("go1"), go1, lambda *a, **k: a[:2])


def test_latency_is_periods_rounded_up_and_checked():
    dt = 0.02
    steps = lambda s: planning_lib.latency_steps(planning_lib.PlanningConfig(latency_s=s), dt)
    assert [steps(0.0), steps(0.005), steps(0.02), steps(0.027), steps(0.06)] == [0, 1, 1, 2, 3]
    with pytest.raises(ValueError, match="latency_s=-0.01"):
        planning_lib.PlanningConfig(latency_s=-0.01)
    with pytest.raises(ValueError, match="latency_s=nan"):
        planning_lib.PlanningConfig(latency_s=float("nan"))


def _counting_planner(nu: int, on_call=None) -> mppi.Planner:
    """A one-step "planner" on Go1 whose plan encodes its calls: action k of call c is
    ``0.01 (c + 1) + 0.001 k`` on every joint (``on_call()`` on the host at each call)."""
    def init(key, plan=None):
        return mppi.MPPIState(jnp.zeros((4, nu)), key, held=jnp.zeros((), jnp.int32))

    def step(state, q_aug, qd):
        if on_call is not None:
            jax.debug.callback(on_call)
        c = state.held
        plan = jnp.broadcast_to((0.01 * (c + 1) + 0.001 * jnp.arange(4))[:, None], (4, nu))
        z = jnp.zeros(1)
        info = mppi.Info(z, z, z[0], plan, jnp.zeros((), jnp.int32), plan[None], z,
                         jnp.full(1, 4, jnp.int32), jnp.zeros((), bool))
        return plan[0], mppi.MPPIState(plan, state.key, held=c + 1), info

    return mppi.Planner(init, step)


def test_the_closed_loop_plays_late_plans_and_resumes_them_across_chunks(go1):
    """On Go1 in MJX (a one-step "planner" that stands still, its plan encoding its calls):
    with a 2-period latency the applied action changes only every other period after the first
    two, the trace keeps the planner's status, and an episode run in chunks equals one run."""
    nu = go1.info.nu
    mx = mjx.put_model(go1.mj)
    walk = dataclasses.replace(cl.SCENARIOS["walk"], seconds=8 * go1.robot.ctrl_dt)
    w = cl.scenario_world(go1, walk)
    planning = planning_lib.make_planning(planning_lib.PlanningConfig(latency_s=0.03),
                                          envs.config("go1"), go1, cl.mjx_step_fn(go1, mx))
    assert planning.latency_steps == 2

    planner = _counting_planner(nu)
    key = jax.random.key(0)
    args = (w.sm, w.mx, w.slots, planning, planner)
    trace = jax.device_get(jax.jit(lambda k: cl.run_episode(
        *args, 8, w.starts, w.values, k))(key))
    a = np.asarray(trace.action)[:, 0]
    np.testing.assert_allclose(a, [0, 0, 0.01, 0.011, 0.02, 0.021, 0.03, 0.031], atol=1e-7)
    carry = ep.start_episode(go1, w.mx, planning, planner, key)
    parts = []
    for first in (0, 3):  # chunks that do not start on a replanning period
        n = 3 if first == 0 else 5
        carry, part = ep.continue_episode(*args, carry, jnp.asarray(first), n, w.starts,
                                          w.values, key)
        parts.append(jax.device_get(part))
    for whole, *pieces in zip(jax.tree.leaves(trace), *(jax.tree.leaves(p) for p in parts)):
        np.testing.assert_allclose(np.concatenate(pieces), whole, atol=1e-6)
    with pytest.raises(ValueError, match="record needs a planner without latency"):
        cl.run_episode(*args, 2, w.starts, w.values, key, record=lambda *a: 0)


def test_the_controllers_own_period_is_the_episodes_first_period_without_the_world(go1):
    """``controller_period`` (what ``stride closed-loop`` times as ``controller_ms``) runs the
    computation of an episode's first period: on time the planner's step, whose action is the
    one the episode applies; with a 2-period latency a replanning period (one call of the planner,
    the initial plan's first action applied); with the observer, its estimate too."""
    nu = go1.info.nu
    mx = mjx.put_model(go1.mj)
    w = cl.scenario_world(go1, dataclasses.replace(cl.SCENARIOS["walk"],
                                                   seconds=2 * go1.robot.ctrl_dt))
    calls = []
    planner, key = _counting_planner(nu, lambda: calls.append(1)), jax.random.key(0)
    for latency, first in ((0.0, 0.01), (0.03, 0.0)):
        planning = planning_lib.make_planning(
            planning_lib.PlanningConfig(latency_s=latency, observer_gain=0.3),
            envs.config("go1"), go1, cl.mjx_step_fn(go1, mx))
        trace = jax.device_get(jax.jit(lambda k: cl.run_episode(
            w.sm, w.mx, w.slots, planning, planner, 1, w.starts, w.values, k))(key))
        carry = jax.jit(lambda k: ep.start_episode(go1, w.mx, planning, planner, k))(key)
        calls.clear()
        u, ps, dist = jax.device_get(jax.jit(lambda c, k: ep.controller_period(
            go1, w.mx, planning, planner, c, k))(carry, key))
        assert len(calls) == 1 and int(ps.held) == 1  # one plan computed
        np.testing.assert_allclose(u, trace.action[0], atol=1e-7)
        np.testing.assert_allclose(u, first, atol=1e-7)
        assert dist.shape == (planning_lib.N_DIST,) and np.all(np.isfinite(dist))
        assert np.any(dist != 0)  # the observer's prediction ran (the standing robot sags)
