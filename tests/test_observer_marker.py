"""experiments/observer_marker.py: falls foretold by the observer's estimate, and false alarms."""

import numpy as np


def _trace(norms, fall_at=None, dt=0.02):
    """A trace whose estimate's linear part has the given norms (along x; the angular entries
    are large and must not count), fallen from step ``fall_at`` on."""
    n = len(norms)
    dist = np.zeros((n, 6))
    dist[:, 0], dist[:, 3:] = norms, 50.0
    fallen = np.zeros(n, bool)
    if fall_at is not None:
        fallen[fall_at:] = True
    return dict(t=dt * np.arange(1, n + 1), fallen=fallen, disturbance=dist)


def test_marker_counts_caught_and_missed_falls_and_the_upright_share_above(experiment):
    mod = experiment("observer_marker")
    rising = np.linspace(0.0, 5.0, 51)  # crosses 3.5 at step 36 (3.5 is not above)
    traces = [_trace(rising, fall_at=46),  # caught, 10 steps before: 0.2 s
              _trace(np.full(50, 1.0), fall_at=20),  # never above: missed
              _trace(np.r_[np.full(45, 1.0), np.full(5, 4.0)]),  # up, 10% of steps above
              _trace(np.full(50, 2.0))]  # up, never above
    r = mod.marker(traces, 3.5)
    assert (r["falls"], r["caught"], r["missed"]) == (2, 1, 1)
    assert np.isclose(r["lead_median_s"], 0.2) and np.isclose(r["lead_min_s"], 0.2)
    assert np.isclose(r["upright_share_above"], 0.05)  # mean of 10% and 0%
    assert (r["upright_episodes"], r["upright_episodes_above"]) == (2, 1)
    # a higher threshold misses the first fall too and raises no alarm where the robot stayed up
    r = mod.marker(traces, 4.2)  # crossed at step 43: 0.06 s before the fall
    assert (r["caught"], r["missed"], r["upright_episodes_above"]) == (1, 1, 0)
    assert np.isclose(r["lead_min_s"], 0.06)
    r = mod.marker(traces, 6.0)
    assert (r["caught"], r["missed"], r["lead_median_s"]) == (0, 2, None)
    # the upward entry alone: these traces' estimates lie along x, so nothing is caught
    r = mod.marker(traces, 3.5, component="vertical")
    assert (r["caught"], r["missed"], r["upright_episodes_above"]) == (0, 2, 0)
    # ... and the floor-plane norm reads them all, as the norm does
    r = mod.marker(traces, 3.5, component="horizontal")
    assert (r["caught"], r["missed"], r["upright_episodes_above"]) == (1, 1, 1)
    # the estimate pointing down: the upward entry never reads it, the downward one does
    down = [dict(tr, disturbance=tr["disturbance"][:, [1, 2, 0, 3, 4, 5]] * [1, 1, -1, 1, 1, 1])
            for tr in traces]  # the x entries moved to z, negated
    r = mod.marker(down, 3.5, component="vertical")
    assert (r["caught"], r["upright_episodes_above"]) == (0, 0)
    r = mod.marker(down, 3.5, component="down")
    assert (r["caught"], r["missed"], r["upright_episodes_above"]) == (1, 1, 1)
    r = mod.marker(down, 3.5, component="horizontal")
    assert (r["caught"], r["upright_episodes_above"]) == (0, 0)


def test_the_replayed_gate_holds_as_the_planner_does_and_shares_grow_with_the_hold(experiment):
    """``handed``: step i reads the estimate after step i - 1, the policy acts while it is above
    the threshold and ``hold`` steps after; ``hand_over_shares`` averages over upright episodes
    only, the hold given in seconds."""
    mod = experiment("observer_marker")
    est = np.array([0.0, 3.0, 1.0, 1.0, 1.0, 1.0, 3.0, 3.0, 1.0, 1.0])
    np.testing.assert_array_equal(mod.handed(est, 2.5, 0),
                                  [0, 0, 1, 0, 0, 0, 0, 1, 1, 0])
    np.testing.assert_array_equal(mod.handed(est, 2.5, 2),
                                  [0, 0, 1, 1, 1, 0, 0, 1, 1, 1])
    assert not mod.handed(est, 3.0, 5).any()  # never above (3.0 is not)
    traces = [_trace(np.r_[0.0, 4.0, np.zeros(98)]),  # up: one crossing
              _trace(np.full(100, 4.0), fall_at=50)]  # fell: not counted
    got = mod.hand_over_shares(traces, 3.5, [0.0, 0.2, 1.0])  # dt 0.02: 0, 10, 50 steps
    assert got == {"0": 0.01, "0.2": 0.11, "1": 0.51}
    assert mod.hand_over_shares(traces[1:], 3.5, [1.0]) == {"1": None}
