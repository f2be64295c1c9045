"""experiments/probes/policy_noise.py: what it reports of its draws."""

import pytest


def test_policy_noise_counts_falls_and_creeps_and_reads_the_last_second_of_those_that_stood(
        experiment):
    """policy_noise.py's per-draw statistics on hand-made traces: a steady draw, one that runs
    past the command and stands, one that runs away and falls."""
    import numpy as np

    mod = experiment("probes/policy_noise")
    T = 150  # 3 s at 50 Hz
    t = np.arange(T) * 0.02
    command = np.zeros((3, T, 3))
    command[..., 0] = 1.0
    v = np.zeros((3, T, 3))
    v[0, :, 0] = 1.0  # steady at the command
    v[1, :, 0] = np.where(t >= 1.5, 1.4, 1.0)  # 0.4 past from 1.5 s, upright
    v[2, :, 0] = np.where(t > 1.5, 1.2, 1.0)  # 0.2 past from 1.5 s ...
    fallen = np.zeros((3, T), bool)
    fallen[2, t >= 2.5] = True  # ... and falls at 2.5 s, lying at 3 m/s
    v[2, t >= 2.5, 0] = 3.0
    s = mod.draw_stats(t, fallen, v, command, over=0.25)
    assert s["falls"] == 1 and s["fall_s"] == [t[t >= 2.5][0]]
    assert s["overspeed"] == 1  # draw 1 alone: draw 2's 3 m/s came after its fall
    # the median of the two that stood (1.0, 1.4), not the fallen draw's 3.0
    assert s["vx_last_s"] == pytest.approx(1.2)
    assert mod.draw_stats(t, fallen, v, command, over=0.1)["overspeed"] == 2
    assert mod.draw_stats(t, np.ones_like(fallen), v, command, over=0.25)["vx_last_s"] is None
