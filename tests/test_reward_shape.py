"""experiments/reward_shape.py: the learned cost against the task's reward along a velocity
shift."""

import numpy as np
import pytest


def test_the_shift_moves_the_base_frames_forward_velocity_alone(experiment):
    """A base yawed and pitched: the shift changes its forward velocity (base frame) by exactly
    ``dv`` and leaves the lateral and vertical ones and every joint velocity as they were."""
    import jax.numpy as jnp

    from stride_jax.control import envs
    from stride_jax.dynamics import integrate
    mod = experiment("reward_shape")
    yaw, pitch = 0.7, 0.2
    quat = integrate.quat_mul(jnp.array([np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)]),
                              jnp.array([np.cos(pitch / 2), 0, np.sin(pitch / 2), 0]))
    q = jnp.concatenate([jnp.array([0.1, -0.2, 0.3]), quat, jnp.zeros(2)])
    qd = jnp.array([0.3, -0.1, 0.05, 0.2, 0.1, -0.3, 1.0, -2.0])
    before = envs.base_signals(q, qd)[0]
    qd2 = mod.shifted(q, qd, 0.4)
    after = envs.base_signals(q, qd2)[0]
    np.testing.assert_allclose(after - before, [0.4, 0.0, 0.0], atol=1e-6)
    np.testing.assert_array_equal(qd2[3:], qd[3:])


def test_governed_clips_every_command_and_keeps_the_times():
    from stride_jax.control.scenarios import SCENARIOS, governed
    sc = governed(SCENARIOS["changes"], ([-1.0, -0.3, -0.5], [1.0, 0.3, 0.5]))
    assert sc.commands == ((0.0, 1.0, 0.0, 0.0), (1.5, 0.3, 0.3, 0.0), (3.0, 1.0, 0.0, 0.5),
                           (4.5, 0.0, 0.0, 0.0))
    assert sc.name == "changes" and sc.seconds == SCENARIOS["changes"].seconds


def test_bad_input_is_named(experiment, tmp_path):
    mod = experiment("reward_shape")
    args = ["--policy", str(tmp_path), "--out", str(tmp_path / "x")]
    with pytest.raises(SystemExit, match="expected three numbers"):
        mod.main(args + ["--learned", "x", "--command", "1,0"])
    with pytest.raises(SystemExit, match="no such file"):
        mod.main(args + ["--learned", str(tmp_path / "none.msgpack")])
