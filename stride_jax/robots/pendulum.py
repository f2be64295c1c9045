"""The 1-DoF torque-controlled pendulum and its bouncing variant (our own MJCF, ``assets/``).

q = 0 hangs down, q = pi is the unstable upright. The torque limit (6 N m) is below the bob's
maximal gravity torque (~10 N m), so the data covers swinging, pumping and braking, not only
holding. A third of the episodes start near the upright so that the saddle is densely sampled.

Hidden stochastic residual (for the phase portrait of the paper's Sec. IV): every episode draws a
torque s * A * exp(-d^2 / (2 * 0.25^2)) with d the angle from the upright, A in [1, 2] N m and
s = +-1 at equal odds (applied as ``qfrc_applied``, recorded in ``qfrc_external``). Away from the
upright it vanishes; near it, given (q, qd, tau), the residual is one of two opposite pushes: the
bimodal "which way does it fall" uncertainty of the saddle. Joint damping and dry friction are
randomised too.
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco

from stride_jax.robots import base


class PendulumParams(NamedTuple):
    key: jax.Array
    qpos0: jax.Array  # [1]
    qvel0: jax.Array  # [1]
    bias: jax.Array  # constant torque (N m)
    amps: jax.Array  # [3] sinusoid amplitudes (N m)
    freqs: jax.Array  # [3] (Hz)
    phases: jax.Array  # [3] (rad)
    noise: jax.Array  # white-noise std (N m)


@dataclasses.dataclass(frozen=True)
class PendulumExplorer:
    """Smooth random torques (a bias, three sinusoids and white noise) from random initial states.

    Attributes:
      q_range: initial angles are uniform in this range (rad), except for the near-upright third.
    """

    q_range: tuple[float, float] = (-math.pi, math.pi)

    def sample(self, key: jax.Array, info: base.ModelInfo) -> PendulumParams:
        k_ep, k_up, k_q, k_qd, k_b, k_a, k_f, k_p, k_n = jax.random.split(key, 9)
        near_up = jax.random.uniform(k_up) < 1 / 3
        q_any = jax.random.uniform(k_q, (1,), minval=self.q_range[0], maxval=self.q_range[1])
        q_up = jnp.pi + jax.random.uniform(k_q, (1,), minval=-0.35, maxval=0.35)
        qd_any = jax.random.uniform(k_qd, (1,), minval=-6.0, maxval=6.0)
        qd_up = jax.random.uniform(k_qd, (1,), minval=-1.0, maxval=1.0)
        return PendulumParams(
            key=k_ep,
            qpos0=jnp.where(near_up, q_up, q_any),
            qvel0=jnp.where(near_up, qd_up, qd_any),
            bias=jax.random.uniform(k_b, minval=-1.0, maxval=1.0),
            amps=jax.random.uniform(k_a, (3,), minval=0.0, maxval=2.5),
            freqs=jax.random.uniform(k_f, (3,), minval=0.1, maxval=2.0),
            phases=jax.random.uniform(k_p, (3,), minval=0.0, maxval=2 * jnp.pi),
            noise=jax.random.uniform(k_n, minval=0.0, maxval=0.5),
        )

    def reset(self, params: PendulumParams, info: base.ModelInfo):
        return params.qpos0, params.qvel0

    def act(self, params: PendulumParams, info: base.ModelInfo, step, qpos, qvel):
        t = step * info.ctrl_dt
        smooth = params.bias + jnp.sum(params.amps * jnp.sin(2 * jnp.pi * params.freqs * t + params.phases))
        white = params.noise * jax.random.normal(jax.random.fold_in(params.key, step))
        return jnp.clip(jnp.atleast_1d(smooth + white), info.ctrl_lo, info.ctrl_hi)


def _no_edit(spec: mujoco.MjSpec) -> None:
    del spec  # our own MJCF is MJX-ready as written


_RANDOMIZATION = base.Randomization(
    damping=(0.5, 2.0),
    frictionloss=(0.5, 2.0),
    bump_nm=(1.0, 2.0),
    bump_at=math.pi,
    bump_width=0.25,
)


def _robot(name: str, filename: str, source: str, explorer: PendulumExplorer,
           feet: tuple[base.Foot, ...] = ()) -> base.Robot:
    return base.Robot(
        name=name,
        source=source,
        load_spec=lambda: base.asset_spec(filename),
        edit_spec=_no_edit,
        joints=("hinge",),
        feet=feet,
        base_body="pole",
        floating_base=False,
        ctrl_dt=0.01,
        home_key=None,
        kp=None,
        kd=None,
        explorer=explorer,
        randomization=_RANDOMIZATION,
        episode_s=5.0,
    )


PENDULUM = _robot("pendulum", "pendulum.xml", "stride_jax/robots/assets/pendulum.xml",
                  PendulumExplorer())
# The wall occupies sin(q) < -0.45 (q in [-2.67, -0.47] rad; positive q swings the bob to -x):
# free-swing starts lie on the other side of it.
PENDULUM_BOUNCING = _robot(
    "pendulum_bouncing", "pendulum_bouncing.xml",
    "stride_jax/robots/assets/pendulum_bouncing.xml (wall at x = 0.5 m)",
    PendulumExplorer(q_range=(-0.4, math.pi)),
    feet=(base.Foot("bob", ("bob",), "tip"),))  # the bob's wall contacts are recorded as a foot's
