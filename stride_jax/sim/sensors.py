"""A real robot's sensors and state estimator: what a controller or a log sees of the true state.

One description of the sensors, :class:`SensorNoise`, serves both places a robot's state is
seen through them: the sim-to-real gap tool's logs of the stand-in "real" robot
(:func:`stride_jax.gap.real.add_noise`, NumPy, a whole logged trajectory at once) and the closed
loop's controller (:func:`measure`, JAX, one control period: what the policy, the planner, its
disturbance observer and its integral action read, ``stride closed-loop --sensor-noise``).

Coordinates are MuJoCo's: a floating base's ``q = [p (3, world), quat (4, w x y z), joints]``,
``qd = [p_dot (3, world), omega (3, body), joint rates]``; a fixed base's are the joints alone.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp

from stride_jax.dynamics.integrate import quat_exp, quat_mul

# the standard deviations and rates of SensorNoise (encoder_bits is a count)
_SCALED = ("encoder_std", "velocity_std", "torque_std", "base_drift", "base_z_std", "tilt_std",
           "linvel_std", "gyro_std")
SPIKE = (2.0, 10.0)  # a glitched joint velocity sample is off by this much (rad/s, either sign)


@dataclasses.dataclass(frozen=True)
class SensorNoise:
    """A real robot's sensors (all standard deviations; 0 disables a term). The defaults are a
    well-instrumented legged robot's (a 14-bit encoder per turn, a kinematic-inertial state
    estimator); ``scaled`` makes it better or worse as a whole.

    Attributes:
      encoder_bits: joint encoder resolution (bits per turn); 0 = no quantisation.
      encoder_std: joint position noise (rad).
      velocity_std: joint velocity estimate noise (rad/s, white at the log rate).
      torque_std: measured torque noise (N m).
      base_drift: random-walk step of the estimator's horizontal position (m per sample).
      base_z_std: estimator height noise (m).
      tilt_std: estimator orientation noise (rad, small random rotation per sample).
      linvel_std: estimator linear velocity noise (m/s).
      gyro_std: angular velocity noise (rad/s).
      outlier_rate: fraction of joint velocity samples replaced by a spike (glitches).
    """

    encoder_bits: int = 14
    encoder_std: float = 2e-4
    velocity_std: float = 0.03
    torque_std: float = 0.2
    base_drift: float = 1e-3
    base_z_std: float = 1e-3
    tilt_std: float = 2e-3
    linvel_std: float = 0.02
    gyro_std: float = 0.01
    outlier_rate: float = 1e-3

    def __post_init__(self):
        if isinstance(self.encoder_bits, bool) or not isinstance(self.encoder_bits, int) or (
                not 0 <= self.encoder_bits <= 32):
            raise ValueError(f"SensorNoise.encoder_bits is {self.encoder_bits!r}: an integer "
                             "0..32 (0: no quantisation)")
        for name in _SCALED + ("outlier_rate",):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"SensorNoise.{name} is {v!r}: a finite number >= 0")
        if self.outlier_rate > 1:
            raise ValueError(f"SensorNoise.outlier_rate is {self.outlier_rate}: a fraction <= 1")

    def scaled(self, factor: float) -> "SensorNoise":
        """Every standard deviation (and the drift) times ``factor``; the encoder's resolution
        and the glitches' rate as they are. ``factor`` 0 is a perfect sensor only in its noise:
        use ``None`` for the exact state."""
        if not (math.isfinite(factor) and factor >= 0):
            raise ValueError(f"sensor noise factor {factor!r}: a finite number >= 0")
        return dataclasses.replace(self, **{n: getattr(self, n) * factor for n in _SCALED})


def seen_through(noise: SensorNoise, factor: float) -> SensorNoise | None:
    """The sensors a controller sees the state through at ``factor`` times ``noise``'s terms
    (the ``--sensor-noise`` and ``--sensors.*`` flags of the closed loop and of select-learned):
    None, the exact state, at factor 0. A negative or NaN factor, or terms changed from the
    defaults while the factor is 0 (they would be silently unused), are clear errors."""
    scaled = noise.scaled(factor)
    if not factor and noise != SensorNoise():
        raise ValueError("--sensors.* set the sensors' terms, which only --sensor-noise > 0 "
                         "uses (1: the terms as given); --sensor-noise is 0")
    return scaled if factor else None


def measure(noise: SensorNoise, q: jax.Array, qd: jax.Array, key: jax.Array,
            floating_base: bool) -> tuple[jax.Array, jax.Array]:
    """``(q, qd)`` of one sample as the sensors and state estimator report them: joint angles
    with noise and quantised to the encoder's resolution, joint rates with noise and glitches
    (``outlier_rate``: a sample off by 2-10 rad/s), and for a floating base its height, its
    orientation (a small random rotation in the body frame, kept unit), its linear velocity and
    its angular velocity (the gyro) each with noise. Each term's draw is its own (``key``), white
    from sample to sample. ``base_drift`` is a random walk over a log (:func:`stride_jax.gap.real.
    add_noise`); one sample has no walk, and nothing that reads :func:`measure` (the policy, the
    planners' models and costs) reads the horizontal position. Pure; jit and vmap it."""
    k_enc, k_vel, k_hit, k_sign, k_size, k_z, k_tilt, k_lin, k_gyro = jax.random.split(key, 9)
    normal = lambda k, shape: jax.random.normal(k, shape, q.dtype)
    jq, jv = (7, 6) if floating_base else (0, 0)
    qj = q[jq:] + noise.encoder_std * normal(k_enc, q[jq:].shape)
    if noise.encoder_bits:
        res = 2 * math.pi / 2 ** noise.encoder_bits
        qj = jnp.round(qj / res) * res
    vj = qd[jv:] + noise.velocity_std * normal(k_vel, qd[jv:].shape)
    if noise.outlier_rate:
        hit = jax.random.bernoulli(k_hit, noise.outlier_rate, vj.shape)
        spike = (jnp.where(jax.random.bernoulli(k_sign, 0.5, vj.shape), 1.0, -1.0)
                 * jax.random.uniform(k_size, vj.shape, vj.dtype, *SPIKE))
        vj = jnp.where(hit, vj + spike, vj)
    q, qd = q.at[jq:].set(qj), qd.at[jv:].set(vj)
    if floating_base:
        quat = quat_mul(q[3:7], quat_exp(noise.tilt_std * normal(k_tilt, (3,))))
        q = q.at[2].add(noise.base_z_std * normal(k_z, ())).at[3:7].set(
            quat / jnp.linalg.norm(quat))
        qd = (qd.at[:3].add(noise.linvel_std * normal(k_lin, (3,)))
              .at[3:6].add(noise.gyro_std * normal(k_gyro, (3,))))
    return q, qd
