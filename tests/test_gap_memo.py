"""The replay memo: a replay asked for again returns the first result without stepping MuJoCo, the
same numbers as replaying it, under every key that changes what a replay computes."""

import mujoco.rollout
import numpy as np
import pytest

from stride_jax.gap import effects, memo, replay, sim
from stride_jax.sim import model


@pytest.fixture(scope="module")
def pend():
    return model.load("pendulum")


@pytest.fixture(autouse=True)
def fresh_memo(monkeypatch):
    monkeypatch.delenv("STRIDE_GAP_MEMO_MB", raising=False)
    memo.clear()
    yield
    memo.clear()


def _logs(n=40, seed=0):
    rng = np.random.default_rng(seed)
    q, qd, cmd = rng.normal(0, 0.5, (n, 1)), rng.normal(0, 1.0, (n, 1)), rng.normal(0, 1.0, (n, 1))
    start = np.arange(0, n - 3, 2)
    return q, qd, cmd, start, np.zeros_like(start)


@pytest.fixture
def rollouts(monkeypatch):
    calls = []
    real = mujoco.rollout.rollout
    monkeypatch.setattr(mujoco.rollout, "rollout", lambda *a, **kw: calls.append(1) or real(*a, **kw))
    return calls


def test_a_replay_asked_for_again_is_not_stepped_and_gives_the_same_numbers(pend, rollouts, monkeypatch):
    q, qd, cmd, start, first = _logs()
    plans = [effects.build(pend, {"damping": [d]}) for d in (0.1, 0.4)]
    a = replay.k_step_many(pend, plans, q, qd, cmd, start, first, 3)
    n = len(rollouts)
    assert n > 0
    b = replay.k_step_many(pend, plans, q, qd, cmd, start, first, 3)
    single = sim.k_step(pend, plans[1], q, qd, cmd, start, first, 3)  # one plan through the other path
    assert len(rollouts) == n, "a repeated replay stepped MuJoCo"
    assert np.array_equal(a[1], b[1]) and np.array_equal(single[1], a[1][1])
    assert memo.stats()["hits"] == 3
    # the same numbers as without the memo
    monkeypatch.setenv("STRIDE_GAP_MEMO_MB", "0")
    off = replay.k_step_many(pend, plans, q, qd, cmd, start, first, 3)
    assert len(rollouts) > n
    assert np.array_equal(off[0], a[0]) and np.array_equal(off[1], a[1])


def test_what_changes_a_replay_changes_its_key(pend, rollouts):
    q, qd, cmd, start, first = _logs()
    plan = effects.build(pend, {"damping": [0.2]})
    sim.k_step(pend, plan, q, qd, cmd, start, first, 2)
    n = len(rollouts)
    cmd2 = cmd.copy()
    cmd2[-1] += 1e-9
    others = [
        (effects.build(pend, {"damping": [0.2 + 1e-12]}), q, qd, cmd, start, first, 2),  # the model
        (effects.build(pend, {"damping": [0.2], "delay": [1]}), q, qd, cmd, start, first, 2),  # a plan field
        (plan, q, qd, cmd, start[1:], first[1:], 2),  # the windows
        (plan, q, qd, cmd, start, first, 3),  # the periods
        (plan, q, qd * 1.0001, cmd, start, first, 2),  # the start states
        (plan, q, qd, cmd2, start, first, 2),  # a logged command
    ]
    for i, (p, *rest) in enumerate(others):
        before = len(rollouts)
        sim.k_step(pend, p, *rest)
        assert len(rollouts) > before, f"case {i} was taken from the memo"
    # ... and a start index of another integer type is the same key
    before = len(rollouts)
    sim.k_step(pend, plan, q, qd, cmd, start.astype(np.int32), first.astype(np.int32), 2)
    assert len(rollouts) == before and n > 0


def test_results_are_read_only_and_a_hit_counts_its_diverged_worlds_again(pend):
    q, qd, cmd, start, first = _logs()
    qd = qd.copy()
    qd[start[2]] = 1e200  # one window diverges
    plan = effects.build(pend, {"damping": [0.3]})
    counts = []
    for _ in range(2):
        before = sim.unstable()["diverged"]
        _, v = sim.k_step(pend, plan, q, qd, cmd, start, first, 2)
        counts.append(sim.unstable()["diverged"] - before)
    assert counts[0] == counts[1] == 2  # NaN from the first period on: counted in each of two periods
    assert np.isnan(v[2]).all() and memo.stats()["hits"] == 1
    with pytest.raises(ValueError):
        v[0] = 0.0
    before = sim.unstable()["diverged"]
    replay.k_step_many(pend, [plan], q, qd, cmd, start, first, 2)
    assert sim.unstable()["diverged"] - before == 2


def test_the_memo_is_bounded_and_can_be_turned_off(pend, rollouts, monkeypatch):
    q, qd, cmd, start, first = _logs()
    monkeypatch.setenv("STRIDE_GAP_MEMO_MB", "0.002")  # 2097 bytes: 7 of the 10 entries (18 windows, 288 bytes)
    for d in np.linspace(0.1, 1.0, 10):
        sim.k_step(pend, effects.build(pend, {"damping": [d]}), q, qd, cmd, start, first, 1)
    assert 0 < memo.stats()["bytes"] <= memo.limit_bytes() < 10 * 288
    n = len(rollouts)
    sim.k_step(pend, effects.build(pend, {"damping": [1.0]}), q, qd, cmd, start, first, 1)  # the newest: kept
    sim.k_step(pend, effects.build(pend, {"damping": [0.1]}), q, qd, cmd, start, first, 1)  # the oldest: evicted
    assert len(rollouts) == n + 1
    monkeypatch.setenv("STRIDE_GAP_MEMO_MB", "0")
    assert not memo.enabled()
    monkeypatch.setenv("STRIDE_GAP_MEMO_MB", "lots")
    with pytest.raises(ValueError, match="STRIDE_GAP_MEMO_MB"):
        memo.limit_bytes()
