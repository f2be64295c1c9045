"""experiments/gap_coverage.py: the sensor-noise terms a coverage run changes."""

import pytest

from stride_jax.gap import real


def test_noise_terms_are_changed_by_name_and_none_means_noise_free(experiment):
    mod = experiment("gap_coverage")
    n = mod.sensor_noise(real, "outlier_rate=0, encoder_bits=0,torque_std=0.5")
    assert (n.outlier_rate, n.encoder_bits, n.torque_std) == (0.0, 0, 0.5)
    assert isinstance(n.encoder_bits, int)
    assert n.velocity_std == real.SensorNoise().velocity_std  # the rest as the default
    assert mod.sensor_noise(real, "") == real.SensorNoise()
    assert mod.sensor_noise(real, "None") is None
    assert "none" in mod.noise_text(None) and "outlier_rate 0" in mod.noise_text(n)
    with pytest.raises(SystemExit, match="gyro_sd"):
        mod.sensor_noise(real, "gyro_sd=0")
    with pytest.raises(SystemExit, match="not a number"):
        mod.sensor_noise(real, "torque_std=low")
