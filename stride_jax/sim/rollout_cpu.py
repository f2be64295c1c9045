"""The CPU backend: MuJoCo's threaded ``mujoco.rollout`` with the same robots, explorers and records.

On a CPU, ``mujoco.rollout`` runs ~30x faster than MJX (Go1: 30-60k vs 1-2k steps/s). It rolls
open-loop controls, so we call it once per control step (``n_substeps`` simulation steps for all
worlds at once, threaded) and compute the explorer's feedback in between with the same jitted JAX
code MJX uses. The recorded quantities come from ``mj_forward`` at the recorded state; its
solution is then handed to the rollout as the warm start, so the first substep solves from the
recorded constraint forces exactly as MJX's split forward/integrate does.
"""

from __future__ import annotations

import functools
import os
from typing import Callable

import jax
import jax.numpy as jnp
import mujoco
import mujoco.rollout
import numpy as np
from mujoco import mjx

from stride_jax.sim import randomize, record, terrain
from stride_jax.sim.model import SimModel, check_open_loop
from stride_jax.sim.rollout_mjx import Episode, _keys_to_data, fallen, sensing_act

_STATE = mujoco.mjtState.mjSTATE_FULLPHYSICS
# Control vector layout (MuJoCo's state order): ctrl, qfrc_applied, xfrc_applied.
_CONTROL = (mujoco.mjtState.mjSTATE_CTRL | mujoco.mjtState.mjSTATE_QFRC_APPLIED
            | mujoco.mjtState.mjSTATE_XFRC_APPLIED)


class _Worlds:
    """A batch of (possibly randomised) worlds stepped with ``mujoco.rollout``."""

    def __init__(self, sm: SimModel, models: list[mujoco.MjModel], qpos: np.ndarray,
                 qvel: np.ndarray, nthread: int):
        self.sm, self.models = sm, models
        m = sm.mj
        self.nq, self.nv = m.nq, m.nv
        self.scratch = mujoco.MjData(m)
        self.datas = [mujoco.MjData(m) for _ in range(max(nthread, 1))]
        self.pool = mujoco.rollout.Rollout(nthread=nthread)
        n = len(models)
        self.state = np.zeros((n, mujoco.mj_stateSize(m, _STATE)))
        for i in range(n):
            mujoco.mj_resetData(models[i], self.scratch)
            self.scratch.qpos[:], self.scratch.qvel[:] = qpos[i], qvel[i]
            mujoco.mj_getState(models[i], self.scratch, self.state[i], _STATE)
        self.warmstart = np.zeros((n, self.nv))
        self.ground_base: list[dict] | None = None

    def set_ground(self, friction: np.ndarray, softness: np.ndarray):
        """Scales each world's foot contacts by the ground under its feet (``[n, F]`` each)."""
        sm = self.sm
        if self.ground_base is None:  # the episode's own values, before any patch
            if len({id(m) for m in self.models}) < len(self.models):
                raise ValueError("ground patches change each world's model: give every world a "
                                 "model of its own")
            self.ground_base = [{k: np.array(getattr(m, k)) for k in randomize.GROUND_FIELDS}
                                for m in self.models]
            self.pair_foot = randomize.pair_feet(self.models[0], sm.geom_foot)
        for i, m in enumerate(self.models):
            new = randomize.apply_ground(self.ground_base[i], sm.geom_foot, self.pair_foot,
                                         friction[i], softness[i], np)
            for k, a in new.items():
                getattr(m, k)[...] = a

    @property
    def qpos(self) -> np.ndarray:  # FULLPHYSICS state: time, qpos, qvel, act, ...
        return self.state[:, 1:1 + self.nq]

    @property
    def qvel(self) -> np.ndarray:
        return self.state[:, 1 + self.nq:1 + self.nq + self.nv]

    @property
    def time(self) -> np.ndarray:
        return self.state[:, 0]

    def step(self, ctrl: np.ndarray, push: np.ndarray, qfrc: np.ndarray, recorded: bool = True
             ) -> list[record.Record]:
        """Records the current state under ``ctrl`` [n, nu], base ``push`` [n, 3] (N) and
        generalised force ``qfrc`` [n, nv], then steps one control period. ``recorded=False``:
        steps without recording (no per-world forward pass; returns no records)."""
        sm, d = self.sm, self.scratch
        xfrc = np.zeros((len(ctrl), sm.mj.nbody, 6))
        xfrc[:, sm.base_body, :3] = push
        recs = []
        for i, m in enumerate(self.models if recorded else ()):
            mujoco.mj_setState(m, d, self.state[i], _STATE)
            d.ctrl[:], d.qfrc_applied[:], d.xfrc_applied[:] = ctrl[i], qfrc[i], xfrc[i]
            d.qacc_warmstart[:] = self.warmstart[i]
            mujoco.mj_forward(m, d)
            recs.append(record.from_mujoco(sm, m, d))
            self.warmstart[i] = d.qacc
        control = np.concatenate([ctrl, qfrc, xfrc.reshape(len(ctrl), -1)], axis=1)
        states, _ = self.pool.rollout(
            self.models, self.datas, self.state, control[:, None, :].repeat(sm.n_substeps, 1),
            control_spec=_CONTROL, initial_warmstart=self.warmstart)
        # Warm start of the next recorded step: the last substep's acceleration, as MuJoCo's
        # own qacc_warmstart would hold it (exact for the Euler integrator).
        dt = sm.mj.opt.timestep
        prev = states[:, -2] if sm.n_substeps > 1 else self.state
        self.warmstart = (states[:, -1, 1 + self.nq:1 + self.nq + self.nv]
                          - prev[:, 1 + self.nq:1 + self.nq + self.nv]) / dt
        self.state = states[:, -1].copy()
        return recs

    def close(self):
        self.pool.close()


def _stack(recs: list[list[record.Record]]) -> record.Record:
    """[T][E] records -> one record of [E, T, ...] arrays (float32, bools kept)."""
    out = {}
    for f in record.FIELDS:
        a = np.stack([np.stack([getattr(r, f) for r in step]) for step in recs], axis=1)
        out[f] = a if a.dtype == bool else a.astype(np.float32)
    return record.Record(**out)


def run(sm: SimModel, models: list[mujoco.MjModel], qpos: np.ndarray, qvel: np.ndarray,
        n_steps: int, policy: Callable, disturb: Callable | None = None,
        nthread: int | None = None, progress: Callable[[int], None] | None = None,
        ground: Callable | None = None) -> tuple[record.Record, np.ndarray]:
    """Rolls ``len(models)`` worlds for ``n_steps`` control steps.

    ``policy(step, qpos [n, nq], qvel [n, nv]) -> ctrl [n, nu]``; ``disturb(time [n], qpos)``
    returns the hidden (push [n, 3], qfrc [n, nv]), none if ``disturb`` is None;
    ``ground(qpos)``, if given, the friction and softness scales ``([n, F], [n, F])`` of the
    ground under each world's feet (every world needs a model of its own, made by
    :func:`~stride_jax.sim.randomize.ground_ready`).
    Returns records ``[n, T, ...]`` and the validity mask ``[n, T]``.
    """
    recs, _, _, valid = _loop(sm, models, qpos, qvel, n_steps, policy, disturb, nthread,
                              progress, True, ground)
    return _stack(recs), valid


def states(sm: SimModel, models: list[mujoco.MjModel], qpos: np.ndarray, qvel: np.ndarray,
           n_steps: int, policy: Callable, disturb: Callable | None = None,
           nthread: int | None = None, ground: Callable | None = None
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`run` without records, several times faster: ``(q [n, T, nq], qd [n, T, nv],
    valid [n, T])`` at the start of each control step."""
    _, q, qd, valid = _loop(sm, models, qpos, qvel, n_steps, policy, disturb, nthread, None,
                            False, ground)
    return q, qd, valid


def _loop(sm, models, qpos, qvel, n_steps, policy, disturb, nthread, progress, recorded,
          ground=None):
    nthread = nthread if nthread is not None else min(len(models), os.cpu_count() or 1)
    worlds = _Worlds(sm, models, qpos, qvel, nthread)
    alive = np.ones(len(models), bool)
    recs, qs, qds, valid = [], [], [], []
    try:
        for step in range(n_steps):
            q, qd = worlds.qpos.copy(), worlds.qvel.copy()
            alive &= ~fallen(sm, q, np) & np.isfinite(q).all(1) & np.isfinite(qd).all(1)
            valid.append(alive.copy())
            qs.append(q)
            qds.append(qd)
            ctrl = np.asarray(policy(step, q, qd), dtype=np.float64)
            if disturb is None:
                push, qfrc = np.zeros((len(q), 3)), np.zeros_like(qd)
            else:
                push, qfrc = (np.asarray(x, dtype=np.float64) for x in disturb(worlds.time, q))
            if ground is not None:
                worlds.set_ground(*(np.asarray(x, np.float64) for x in ground(q)))
            recs.append(worlds.step(ctrl, push, qfrc, recorded))
            if progress:
                progress(1)
    finally:
        worlds.close()
    return recs, np.stack(qs, 1), np.stack(qds, 1), np.stack(valid, axis=1)


@functools.lru_cache(maxsize=None)
def _jitted(sm: SimModel, sloped: bool = False):
    """The per-episode draws, the vmapped explorer (told each world's gravity on ``sloped``
    data, where it senses it: :func:`sensing_act`) and the pushes, jitted once per
    robot."""
    robot, info, explorer = sm.robot, sm.info, sm.robot.explorer
    sensing = sensing_act(explorer, sloped)

    def draw(k, episode_s):
        key_rand, key_explore = jax.random.split(k)
        rand = randomize.sample(key_rand, robot.randomization, episode_s)
        params = explorer.sample(key_explore, info)
        qpos, qvel = explorer.reset(params, info)
        return rand, params, qpos, qvel

    act = jax.vmap(lambda p, s, q, qd, down: sensing(p, info, s, q, qd, down),
                   in_axes=(0, None, 0, 0, 0))
    disturb = jax.vmap(lambda v, t, q: randomize.disturbance(v, robot.randomization, t, q,
                                                             sm.mj.nv))
    return jax.jit(jax.vmap(draw, in_axes=(0, None))), jax.jit(act), jax.jit(disturb)


@functools.lru_cache(maxsize=None)
def _patches(sm: SimModel, r) -> Callable:
    """The vmapped patch lookup, jitted once per (robot, randomisation): built per collection,
    it compiled again each time (~2 s of a 3-episode Go1 collection on 2 cores)."""
    mx = mjx.put_model(sm.mj)
    return jax.jit(jax.vmap(lambda v, q: randomize.foot_patches(
        v, r, randomize.foot_xy(mx, sm.foot_sites, q))))


def ground_fn(sm: SimModel, r, rand: randomize.RandValues) -> Callable:
    """``ground(qpos [n, nq]) -> (friction, softness)`` ``[n, F]`` each: the patches under the
    feet of worlds whose hidden values are ``rand`` (batched over worlds)."""
    patches = _patches(sm, r)
    rand = jax.tree.map(jnp.asarray, rand)
    return lambda q: patches(rand, jnp.asarray(q, jnp.float32))


@functools.lru_cache(maxsize=None)
def _heights(r) -> Callable:
    return jax.jit(jax.vmap(lambda seed: terrain.heights(seed, r)))


_HEIGHT_CHUNK = 8


def _height_data(r, terrain_seed: np.ndarray) -> list[np.ndarray]:
    """The heightfield data ``[grid^2]`` of each world (its episode's terrain seed), each
    distinct field computed once, in padded batches of :data:`_HEIGHT_CHUNK`: the field's
    Fourier features take ``grid^2 x FEATURES`` floats per world (41 MB on the 20 m field), and
    one batch of an evaluation's 2048 re-simulated worlds asked for 168 GB (measured: out of
    memory). The values are bitwise those of one batch of all worlds (checked for batches of 2
    to 16 against 19 at once), so datasets stay as they were."""
    seeds, which = np.unique(np.asarray(terrain_seed), return_inverse=True)
    fields = []
    for i in range(0, len(seeds), _HEIGHT_CHUNK):
        chunk = seeds[i:i + _HEIGHT_CHUNK]
        padded = np.concatenate([chunk, np.repeat(chunk[-1:], _HEIGHT_CHUNK - len(chunk))])
        fields.extend(np.asarray(_heights(r)(jnp.asarray(padded)), np.float64)[:len(chunk)])
    return [fields[i] for i in which.reshape(-1)]


def randomized_worlds(sm: SimModel, r, rand: randomize.RandValues
                      ) -> tuple[list[mujoco.MjModel], Callable | None]:
    """``(models, ground)``: one randomised copy of the robot's model per world of ``rand``
    (batched hidden values, ``r`` their ranges) and, where the ground varies along the path, the
    :func:`ground_fn` that :func:`run` and :func:`states` take (``None`` otherwise).
    With rough ground (``r.rough``), ``sm`` must be :func:`stride_jax.sim.terrain.rough_model`'s
    (the one to roll the worlds with): each world gets its episode's heights."""
    if r.rough and mujoco.mj_name2id(sm.mj, mujoco.mjtObj.mjOBJ_HFIELD, terrain.NAME) < 0:
        raise ValueError("rough ground: pass the model with the heightfield, "
                         "stride_jax.sim.terrain.rough_model(sm, r), and roll the worlds with it")
    mj = randomize.ground_ready(sm.mj, sm.geom_foot) if r.patches else sm.mj
    fields = randomize.nominal_fields(mj)
    rand_np = jax.tree.map(np.asarray, rand)
    n = len(rand_np.friction)
    payload_body = randomize.payload_body_id(sm, r)
    models = [randomize.apply_mujoco(mj, fields, jax.tree.map(lambda a: a[i], rand_np),
                                     payload_body) for i in range(n)]
    if r.rough:
        for m, h in zip(models, _height_data(r, rand_np.terrain_seed)):
            m.hfield_data[...] = h
    if r.sloped:
        for m, down in zip(models, rand_np.down):
            randomize.tilt_mujoco(m, down)
    return models, (ground_fn(sm, r, rand_np) if r.patches else None)


def collect(sm: SimModel, key: jax.Array, n_episodes: int, n_steps: int, randomized: bool = True,
            nthread: int | None = None, progress: Callable[[int], None] | None = None,
            part: slice = slice(None)) -> Episode:
    """Collects episodes exactly as :func:`stride_jax.sim.rollout_mjx.collect` describes them
    (``part`` included).

    Per-episode draws (randomisation, explorer parameters, initial state) use the same keys and
    code as the MJX backend, so both backends simulate the same worlds from the same seed.
    """
    if randomized and sm.robot.randomization.rough:
        sm = terrain.rough_model(sm, sm.robot.randomization)
    draw, act, disturb_fn = _jitted(sm, randomized and sm.robot.randomization.sloped)
    episode_s = n_steps * sm.robot.ctrl_dt
    keys = jax.random.split(key, n_episodes)[part]
    n_episodes = keys.shape[0]
    rand, params, qpos, qvel = draw(keys, episode_s)
    rand_np = jax.tree.map(np.asarray, rand)
    models, ground = (randomized_worlds(sm, sm.robot.randomization, rand_np) if randomized
                      else ([sm.mj] * n_episodes, None))
    policy = lambda step, q, qd: act(params, step, jnp.asarray(q, jnp.float32),
                                     jnp.asarray(qd, jnp.float32), rand.down)
    disturb = (lambda t, q: disturb_fn(rand, jnp.asarray(t, jnp.float32),
                                       jnp.asarray(q, jnp.float32))) if randomized else None
    recs, valid = run(sm, models, np.asarray(qpos, np.float64), np.asarray(qvel, np.float64),
                      n_steps, policy, disturb, nthread, progress, ground)
    return Episode(recs, valid, rand_np, jax.device_get(_keys_to_data(params)))


def simulate(sm: SimModel, qpos: np.ndarray, qvel: np.ndarray, ctrl: np.ndarray) -> record.Record:
    """Open-loop rollout of the nominal model from one state under ``ctrl`` ``[T, nu]``."""
    qpos, qvel, ctrl = check_open_loop(sm, qpos, qvel, ctrl)
    recs, _ = run(sm, [sm.mj], qpos[None], qvel[None], len(ctrl),
                  lambda step, q, qd: ctrl[step][None], nthread=1)
    return jax.tree.map(lambda a: a[0], recs)
