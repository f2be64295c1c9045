"""MJX's Warp implementation (MuJoCo Warp, ``impl="warp"``) as a data backend beside MJX's JAX one.

The episode, explorer, randomization and recording are those of :mod:`stride_jax.sim.rollout_mjx`;
only the physics differs: ``mjx.step`` runs MuJoCo Warp's kernels (CUDA on a GPU, LLVM on a CPU)
through JAX's FFI, vmapped over worlds by MJX's custom batching rule.

Differences that shape the code here:

- Warp allocates its contacts for all worlds at once (``naconmax``), so a collection function is
  built for one number of worlds (:func:`layout`), and a world's contacts are found through its
  constraint rows (``efc.id`` names the contact of each row) rather than through fixed slots.
- MuJoCo Warp has no separate integrator entry in MJX, so a control period's first step is a full
  ``mjx.step``; its forward-pass quantities (``qacc``, the force split, body poses) are those of
  the state before the step, as MuJoCo's ``mj_step`` leaves them, and the record pairs them with
  that state (:func:`control_step`).
- A heightfield's heights cannot differ per world (``hfield_data`` is not a batched field of
  MuJoCo Warp), so rough ground is refused with a clear error.

``warp-lang`` is an optional dependency (``pip install warp-lang``); :func:`require` says so.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import mjx

from stride_jax.sim import record
from stride_jax.sim.model import SimModel

# Contacts per foot geom a world may hold at most (a box on a plane makes up to 4); MuJoCo Warp
# drops contacts beyond ``naconmax`` (summed over worlds) and warns. Measured: 4 per foot (not per
# foot geom) overflowed on G1, whose 2 feet have 6 geoms.
CONTACTS_PER_GEOM = 4
_PYRAMIDAL = int(mujoco.mjtConstraint.mjCNSTR_CONTACT_PYRAMIDAL)


def installed() -> bool:
    try:
        import warp  # noqa: F401
    except ImportError:
        return False
    return True


def require() -> None:
    if not installed():
        raise RuntimeError("backend 'warp' needs the warp-lang package (pip install warp-lang); "
                           "use backend 'mjx' or 'cpu' without it")


def check_devices() -> None:
    """MuJoCo Warp's foreign call cannot be split over devices by XLA, and under ``shard_map`` it
    crashed (SIGSEGV on two H200s): one device per process."""
    n = len(jax.local_devices())
    if n > 1:
        raise ValueError(
            f"backend 'warp' runs on one device per process and this process sees {n}; start "
            "one process per GPU (CUDA_VISIBLE_DEVICES and --distributed.*, see "
            "stride_jax.distributed) or use backend 'mjx'")


class WarpLayout(NamedTuple):
    """What a Warp collection needs besides the model: its data template and the feet's geoms."""

    template: mjx.Data  # one world's data, allocated for ``worlds`` worlds' contacts
    geom_foot: np.ndarray  # [ngeom] foot index of each geom, or -1


def check_model(m: mujoco.MjModel) -> None:
    """Refuses what this backend does not record faithfully."""
    if m.nhfield:
        raise ValueError("backend 'warp': rough ground (a heightfield) is not supported, since "
                         "MuJoCo Warp cannot give each world its own heights; use backend 'mjx'")
    if m.opt.cone != mujoco.mjtCone.mjCONE_PYRAMIDAL:
        raise ValueError("backend 'warp' records foot forces from pyramidal contacts; "
                         f"this model's cone is {mujoco.mjtCone(m.opt.cone).name}")


def put_model(m: mujoco.MjModel) -> mjx.Model:
    """The Warp model of ``m``. Its warnings of a solver stopping at its iteration cap are off
    (the robots' few-iteration solvers, as in MJX, reach it by design, and Warp would print a
    line per step); warnings of contacts or constraint rows overflowing their buffers stay on."""
    require()
    check_model(m)
    from mujoco.mjx.third_party.mujoco_warp._src.types import OverflowType
    mx = mjx.put_model(m, impl="warp")
    quiet = int(OverflowType.ALL & ~(OverflowType.ITERATIONS | OverflowType.LS_ITERATIONS))
    return mx.replace(opt=mx.opt.replace(_impl=mx.opt._impl.replace(warn_overflow=quiet)))


def layout(sm: SimModel, m: mujoco.MjModel, worlds: int) -> WarpLayout:
    """The data template for ``worlds`` worlds; ``m`` is the MuJoCo model the worlds start from."""
    require()
    foot_geoms = int((np.asarray(sm.geom_foot) >= 0).sum())
    per_world = CONTACTS_PER_GEOM * foot_geoms if foot_geoms else max(4, m.ngeom)
    njmax = 2 * m.nv + 8 * per_world  # joint limits and friction, plus 4 pyramid rows per contact
    template = mjx.make_data(m, impl="warp", naconmax=worlds * per_world, njmax=njmax)
    return WarpLayout(template, np.asarray(sm.geom_foot))


def foot_force(sm: SimModel, lay: WarpLayout, d: mjx.Data) -> jax.Array:
    """``[nfeet]`` normal force per foot: the sum of its pyramidal contact rows' forces.

    ``d`` is one world's data after a step (inside the vmap over worlds); its constraint rows are
    its own, while the contact table is shared by all worlds and indexed by ``efc.id``.
    """
    if not sm.nfeet:
        return jnp.zeros((0,))
    impl = d._impl
    force, kind, cid = impl.efc__force, impl.efc__type, impl.efc__id
    geom = impl.contact__geom
    owner = jnp.asarray(lay.geom_foot)
    g = geom[jnp.clip(cid, 0, geom.shape[0] - 1)]
    foot = jnp.maximum(owner[g[:, 0]], owner[g[:, 1]])
    used = jnp.arange(force.shape[-1]) < jnp.reshape(impl.nefc, ())
    keep = used & (kind == _PYRAMIDAL) & (foot >= 0)
    return jax.ops.segment_sum(jnp.where(keep, force, 0.0), jnp.where(keep, foot, 0),
                               num_segments=sm.nfeet)


def control_step(sm: SimModel, lay: WarpLayout, mx: mjx.Model, d: mjx.Data, ctrl: jax.Array,
                 push: jax.Array, qfrc: jax.Array) -> tuple[mjx.Data, record.Record]:
    """One control period: ``n_substeps`` Warp steps with ``ctrl`` and the disturbance held; the
    record is the state before the period with the first step's forward-pass quantities."""
    xfrc = d.xfrc_applied.at[sm.base_body, :3].set(push)
    d = d.replace(ctrl=ctrl, xfrc_applied=xfrc, qfrc_applied=qfrc)
    d1 = mjx.step(mx, d)
    rec = record.from_forward(sm, d1, foot_force(sm, lay, d1), mx.opt.gravity, before=d)
    d1 = jax.lax.fori_loop(1, sm.n_substeps, lambda _, dd: mjx.step(mx, dd), d1)
    return d1, rec
