"""Batched MJX rollouts: one world is written once, vmapped over worlds, sharded over devices.

A world's episode is a ``lax.scan`` over control steps. Each control step runs ``n_substeps``
simulation steps with the control held; the first is split into ``mjx.forward`` (whose quantities
are recorded) and the integrator, so recording costs no extra forward pass.

``impl="warp"`` runs the same episodes on MuJoCo Warp's kernels instead of MJX's JAX physics
(:mod:`stride_jax.sim.mjx_warp`); everything else (explorer, randomization, records) is shared.
"""

from __future__ import annotations

import concurrent.futures
import functools
import threading
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from jax.sharding import NamedSharding
from mujoco import mjx

from stride_jax import _env, distributed
from stride_jax.sim import mjx_warp, randomize, record, terrain
from stride_jax.sim.model import SimModel, check_open_loop


class Episode(NamedTuple):
    """One world's rollout: per-step records plus episode-level values (for analysis only)."""

    records: record.Record  # each field [T, ...]
    valid: jax.Array  # [T] bool: not fallen and finite up to and including this step
    rand: randomize.RandValues
    explore: Any  # the explorer's episode parameters


def sensing_act(explorer, sloped: bool) -> Callable:
    """``act(params, info, step, q, qd, down)``: the explorer's ``act``, told each world's
    gravity direction ``down`` where the data are ``sloped`` and it senses gravity
    (``senses_gravity``: :class:`stride_jax.control.walk.PolicyExplorer`); otherwise ``down``
    is dropped."""
    if sloped and getattr(explorer, "senses_gravity", False):
        return lambda p, info, s, q, qd, down: explorer.act(p, info, s, q, qd, gravity=down)
    return lambda p, info, s, q, qd, down: explorer.act(p, info, s, q, qd)


def _integrate(mx: mjx.Model, d: mjx.Data) -> mjx.Data:
    if mx.opt.integrator == mujoco.mjtIntegrator.mjINT_EULER:
        return mjx.euler(mx, d)
    if mx.opt.integrator == mujoco.mjtIntegrator.mjINT_IMPLICITFAST:
        return mjx.implicit(mx, d)
    raise NotImplementedError(f"integrator {mx.opt.integrator} is not supported by stride_jax")


def fallen(sm: SimModel, qpos, xp=jnp):
    """Whether a floating-base robot is down: base too low or tilted too far from upright.

    ``qpos`` is ``[..., nq]``; ``xp`` is ``jax.numpy`` or ``numpy``.
    """
    if not sm.robot.floating_base:
        return xp.zeros(qpos.shape[:-1], bool)
    x, y = qpos[..., 4], qpos[..., 5]
    cos_tilt = 1.0 - 2.0 * (x * x + y * y)  # z-axis of the base against world z
    return (qpos[..., 2] < sm.robot.min_base_height) | (cos_tilt < np.cos(sm.robot.max_tilt))


# MJX's matrix products in full float32. A GPU runs float32 products in TF32 unless asked, and
# then the records miss MuJoCo's equation of motion by 1.7% of the force scale and contact forces
# by up to 120 N (Go1 on an H100, `make test-gpu`, results/gpu_tests/). Traced under it, the
# physics of data, closed loops and benchmarks is float32; on a CPU it changes nothing.
PRECISION = "highest"


def control_step(sm: SimModel, layout: record.ContactLayout, mx: mjx.Model, d: mjx.Data,
                 ctrl: jax.Array, dist: randomize.Disturbance) -> tuple[mjx.Data, record.Record]:
    """Holds ``ctrl`` and the disturbance (base push, generalised force) for one control period."""
    with jax.default_matmul_precision(PRECISION):
        xfrc = d.xfrc_applied.at[sm.base_body, :3].set(dist.push)
        d = d.replace(ctrl=ctrl, xfrc_applied=xfrc, qfrc_applied=dist.qfrc)
        d = mjx.forward(mx, d)
        rec = record.from_mjx(sm, d, layout, mx.opt.gravity)
        d = _integrate(mx, d)
        d = jax.lax.fori_loop(1, sm.n_substeps, lambda _, dd: mjx.step(mx, dd), d)
    return d, rec


def run_episode(sm: SimModel, layout: record.ContactLayout | mjx_warp.WarpLayout, mx: mjx.Model,
                qpos: jax.Array, qvel: jax.Array, n_steps: int, policy: Callable, disturb: Callable,
                ground: Callable | None = None) -> tuple[record.Record, jax.Array]:
    """Rolls one world out for ``n_steps`` control steps under ``policy(step, qpos, qvel)``.

    ``disturb(time, qpos)`` returns the hidden :class:`~stride_jax.sim.randomize.Disturbance`;
    ``ground(mx, qpos)``, if given, the model of this control step (the ground under the feet).

    ``layout`` is a :class:`~stride_jax.sim.mjx_warp.WarpLayout` for a Warp model.

    Returns the records ``[T, ...]`` and the validity mask ``[T]``.
    """
    warp = isinstance(layout, mjx_warp.WarpLayout)
    d = (layout.template if warp else mjx.make_data(mx)).replace(qpos=qpos, qvel=qvel)

    def body(carry, step):
        d, alive = carry
        alive = alive & ~fallen(sm, d.qpos) & jnp.all(jnp.isfinite(d.qpos)) & jnp.all(
            jnp.isfinite(d.qvel))
        ctrl = policy(step, d.qpos, d.qvel)
        mx_t = mx if ground is None else ground(mx, d.qpos)
        dist = disturb(d.time, d.qpos)
        if warp:  # Warp's kernels compute in float32 whatever XLA's matmul precision
            d, rec = mjx_warp.control_step(sm, layout, mx_t, d, ctrl, dist.push, dist.qfrc)
        else:
            d, rec = control_step(sm, layout, mx_t, d, ctrl, dist)
        return (d, alive), (rec, alive)

    _, (recs, valid) = jax.lax.scan(body, (d, jnp.ones((), bool)), jnp.arange(n_steps))
    return recs, valid


IMPLS = ("jax", "warp")
BACKENDS = {"mjx": "jax", "warp": "warp"}  # data backend name -> MJX implementation


def _check_impl(impl: str, worlds: int | None) -> None:
    if impl not in IMPLS:
        raise ValueError(f"unknown MJX implementation {impl!r}; use one of {IMPLS}")
    if impl == "warp" and not worlds:
        raise ValueError("impl='warp' needs the number of worlds (its contacts are allocated "
                         "for all worlds at once)")


def make_collect_fn(sm: SimModel, n_steps: int, randomized: bool = True, impl: str = "jax",
                    worlds: int | None = None) -> Callable:
    """A pure ``episode(key) -> Episode`` for one world, exploring with the robot's explorer.

    ``impl``: MJX's ``jax`` physics or MuJoCo Warp's (``warp``, which needs ``worlds``, the number
    of worlds the function is vmapped over).
    """
    _check_impl(impl, worlds)
    explorer, info, robot = sm.robot.explorer, sm.info, sm.robot
    r = robot.randomization
    patches = randomized and r.patches
    rough = randomized and r.rough
    if rough:  # the heightfield in place of the floor; its heights are set per world below
        sm = terrain.rough_model(sm, r)
    mj = randomize.ground_ready(sm.mj, sm.geom_foot) if patches else sm.mj
    if impl == "warp":
        mx0 = mjx_warp.put_model(mj)
        layout = mjx_warp.layout(sm, mj, worlds)
    else:
        mx0 = mjx.put_model(mj)
        layout = record.mjx_contact_layout(sm, mx0)
    # MJX's own kinematics find the patches under the feet, so both impls look up the same ones
    mx_kin = (mx0 if impl == "jax" else mjx.put_model(mj)) if patches else None
    fields = randomize.nominal_fields(mj)
    payload_body = randomize.payload_body_id(sm, r)
    pair_foot = randomize.pair_feet(mj, sm.geom_foot)
    episode_s = n_steps * robot.ctrl_dt
    act = sensing_act(explorer, randomized and r.sloped)

    def episode(key: jax.Array) -> Episode:
        key_rand, key_explore = jax.random.split(key)
        rand = randomize.sample(key_rand, robot.randomization, episode_s)
        mx = randomize.apply_mjx(mx0, fields, rand, payload_body) if randomized else mx0
        if randomized and r.sloped:
            mx = randomize.tilt_mjx(mx, rand.down)
        if rough:
            mx = mx.replace(hfield_data=terrain.heights(rand.terrain_seed, r).astype(
                mx0.hfield_data.dtype))
        params = explorer.sample(key_explore, info)
        qpos, qvel = explorer.reset(params, info)
        policy = lambda step, q, qd: act(params, info, step, q, qd, rand.down)
        disturb = functools.partial(_disturbance, sm, rand if randomized else None)
        ground = None
        if patches:
            here = {k: getattr(mx, k) for k in randomize.GROUND_FIELDS}

            def ground(mx_, q):
                xy = randomize.foot_xy(mx_kin, sm.foot_sites, q)
                fr, so = randomize.foot_patches(rand, r, xy)
                new = randomize.apply_ground(here, sm.geom_foot, pair_foot, fr, so)
                return mx_.replace(**{k: a.astype(here[k].dtype) for k, a in new.items()})
        recs, valid = run_episode(sm, layout, mx, qpos, qvel, n_steps, policy, disturb, ground)
        return Episode(recs, valid, rand, params)

    return episode


def _disturbance(sm: SimModel, rand: randomize.RandValues | None, t: jax.Array,
                 qpos: jax.Array) -> randomize.Disturbance:
    if rand is None:
        return randomize.Disturbance(jnp.zeros(3), jnp.zeros(sm.mj.nv))
    return randomize.disturbance(rand, sm.robot.randomization, t, qpos, sm.mj.nv)


def _keys_to_data(tree):
    """Typed PRNG keys cannot leave JAX; store their raw data instead."""
    is_key = lambda x: jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key)
    return jax.tree.map(lambda x: jax.random.key_data(x) if is_key(x) else x, tree)


def mjx_devices() -> list:
    """The local devices MJX's physics may run on side by side: all of them, but one where they
    are host devices of a CPU whose XLA pool would hang on their batched Cholesky
    (:func:`stride_jax._env.side_by_side_lapack`)."""
    return _env.side_by_side_lapack(jax.local_devices())


def world_sharding(n_worlds: int, devices: list | None = None) -> NamedSharding | None:
    """Shards a leading world axis over ``devices`` (all local devices; None on a single one)."""
    return distributed.split_leading("worlds", devices, n_worlds)


_COLLECT_FNS: dict = {}


def collect_fn(sm: SimModel, n_steps: int, randomized: bool = True, impl: str = "jax",
               worlds: int | None = None) -> Callable:
    """The jitted ``episodes(keys [B]) -> Episode`` of :func:`make_collect_fn`, vmapped over worlds.
    Built once per (model, episode length, randomization, impl, worlds), so that repeated
    collections in one process (data in chunks, benchmarks timing a second call) reuse its
    compilation instead of tracing anew. On several local devices MJX's physics is split over them
    by XLA's partitioner (the keys sharded over the devices, as :func:`collect` passes them).

    ``worlds`` (``B``): needed by ``impl="warp"`` (its contacts are allocated per call); ignored
    otherwise. MuJoCo Warp's foreign call cannot be partitioned by XLA, and under ``shard_map``
    it crashed (SIGSEGV on two H200s, as did MJX's physics), so ``warp`` runs on one device per
    process: several GPUs take one process each (:mod:`stride_jax.distributed`).
    """
    if impl == "warp":
        mjx_warp.check_devices()
    k = (id(sm), n_steps, randomized, impl, worlds if impl == "warp" else None)
    hit = _COLLECT_FNS.get(k)
    if hit is None or hit[0] is not sm:  # the model kept beside its id: an id is never reused
        if len(_COLLECT_FNS) >= 8:
            _COLLECT_FNS.clear()
        fn = jax.vmap(make_collect_fn(sm, n_steps, randomized, impl, worlds))
        hit = _COLLECT_FNS[k] = (sm, jax.jit(fn))
    return hit[1]


SPLITS = ("shard", "threads")  # how one process's local devices share a collection


def check_split(split: str) -> None:
    """A clear error for a ``split`` that is not one of :data:`SPLITS`."""
    if split not in SPLITS:
        raise ValueError(f"split={split!r}: use one of {', '.join(SPLITS)}")


def _placement(batch: int, devices: list):
    """Where one partitioned call's keys go: split over ``devices``, or on the one device."""
    return world_sharding(batch, devices) if len(devices) > 1 else devices[0]


def collect(sm: SimModel, key: jax.Array, n_episodes: int, n_steps: int, batch: int | None = None,
            randomized: bool = True, progress: Callable[[int], None] | None = None,
            part: slice = slice(None), impl: str = "jax", split: str = "threads") -> Episode:
    """Collects ``n_episodes`` episodes of ``n_steps`` control steps, ``batch`` worlds at a time.

    Each batch is one jitted, vmapped call. The next batch is dispatched before the last one's
    records are copied to the host, so the copy overlaps the simulation. Returns numpy arrays with
    a leading episode axis. ``progress(n)`` is called after each batch with its size.
    ``part``: only these of the ``n_episodes`` (each episode's draws come from its own key, so a
    part is exactly those episodes of the whole; several processes each make one).
    ``impl``: ``jax`` (MJX's physics) or ``warp`` (MuJoCo Warp's; :mod:`~stride_jax.sim.mjx_warp`).
    ``split``, where the process sees several devices: ``shard`` splits each call's worlds over
    them through XLA's partitioner (one program; one host thread copies every device's records);
    ``threads`` gives each device a contiguous share of the episodes, its own program of
    ``batch / devices`` worlds per call, and its own host thread dispatching the calls and
    copying the records, as one process per device does (compiled once per device). The same
    records either way.
    """
    check_split(split)
    keys = jax.random.split(key, n_episodes)[part]
    n_episodes = keys.shape[0]
    batch = min(batch or n_episodes, n_episodes)
    devices = mjx_devices()
    if split == "shard" or len(devices) == 1:
        fn = collect_fn(sm, n_steps, randomized, impl, batch)
        return _pipeline(fn, keys, batch, _placement(batch, devices), progress)
    per = -(-n_episodes // len(devices))  # each device's share of the episodes
    calls = min(-(-batch // len(devices)), per)  # worlds per call on each device
    fn = collect_fn(sm, n_steps, randomized, impl, calls)
    lock = threading.Lock()

    def tick(n):
        with lock:
            progress(n)

    shares = [(d, keys[i * per:(i + 1) * per]) for i, d in enumerate(devices)
              if i * per < n_episodes]
    with concurrent.futures.ThreadPoolExecutor(len(shares)) as pool:
        parts = list(pool.map(lambda s: _pipeline(fn, s[1], calls, s[0], progress and tick),
                              shares))
    return jax.tree.map(lambda *a: np.concatenate(a), *parts)


def device_call(sm: SimModel, n_steps: int, batch: int, randomized: bool = True,
                impl: str = "jax", split: str = "threads",
                key: jax.Array | None = None) -> Callable[[], Any]:
    """One call of :func:`collect`'s over ``batch`` worlds on the local devices, split as
    ``split`` splits them, blocked on and nothing copied to the host: the device-side part of a
    collection, which the throughput benchmarks time. Compiled on its first call."""
    check_split(split)
    devices = mjx_devices()
    keys = jax.random.split(jax.random.key(1) if key is None else key, batch)
    if split == "shard" or len(devices) == 1:
        fn = collect_fn(sm, n_steps, randomized, impl, batch)
        keys = jax.device_put(keys, _placement(batch, devices))
        return lambda: jax.block_until_ready(fn(keys))
    if batch % len(devices):
        raise ValueError(f"{batch} worlds do not split evenly over {len(devices)} devices; "
                         f"use a multiple of {len(devices)}")
    fn = collect_fn(sm, n_steps, randomized, impl, batch // len(devices))
    shares = [jax.device_put(k, d) for k, d in zip(jnp.split(keys, len(devices)), devices)]
    return lambda: jax.block_until_ready([fn(k) for k in shares])  # dispatched, run together


def _pipeline(fn: Callable, keys: jax.Array, batch: int, place, progress) -> Episode:
    """``fn`` over ``keys`` in calls of ``batch`` worlds placed by ``place`` (a sharding or a
    device); each call is dispatched before the previous one's records are copied."""
    out, pending = [], None

    def fetch(job):
        ep, n = job
        out.append(jax.tree.map(lambda a: np.asarray(a)[:n], jax.device_get(_keys_to_data(ep))))
        if progress:
            progress(n)

    for start in range(0, keys.shape[0], batch):
        k = keys[start:start + batch]
        n = k.shape[0]
        if n < batch:  # pad the last batch to the compiled shape
            k = jnp.concatenate([k, jnp.repeat(k[-1:], batch - n, axis=0)])
        job = (fn(jax.device_put(k, place)), n)  # dispatched: runs while the previous batch is copied
        if pending is not None:
            fetch(pending)
        pending = job
    fetch(pending)
    return jax.tree.map(lambda *a: np.concatenate(a), *out)


def simulate(sm: SimModel, qpos: np.ndarray, qvel: np.ndarray, ctrl: np.ndarray,
             impl: str = "jax") -> record.Record:
    """Open-loop rollout of the nominal model from one state under ``ctrl`` ``[T, nu]``."""
    qpos, qvel, ctrl = check_open_loop(sm, qpos, qvel, ctrl)
    _check_impl(impl, 1)
    if impl == "warp":
        mx, layout = mjx_warp.put_model(sm.mj), mjx_warp.layout(sm, sm.mj, 1)
    else:
        mx = mjx.put_model(sm.mj)
        layout = record.mjx_contact_layout(sm, mx)
    ctrl = jnp.asarray(ctrl, jnp.float32)
    policy = lambda step, q, qd: ctrl[step]
    fn = jax.jit(lambda q, qd: run_episode(sm, layout, mx, q, qd, ctrl.shape[0], policy,
                                           functools.partial(_disturbance, sm, None))[0])
    return jax.device_get(fn(jnp.asarray(qpos), jnp.asarray(qvel)))
