"""Replays already made, kept by what determines them, so that no diagnosis replays one twice.

A diagnosis replays the same hypothesis on the same windows from several places: the baseline
at every scalar fit's nominal grid node, the calibration's least squares at a start another
search has already replayed, the nominal-value check at the residual the detection test has just
computed. Measured on the speed benchmark's Go1 diagnosis (12 x 8 s logs, shipped model, default
preset; ``results/gap_speed.md``, session 64): 10.4% of its 1.14 M replayed window-periods were
repeats, about 30 s of its 5 minutes. MuJoCo's replay of one world is deterministic and does not
depend on the batch it runs in (:mod:`stride_jax.gap.replay`, tested bit for bit), so a repeat
can return the first result unchanged.

The key is a digest of everything the replay reads: the simulated model (every field of the
:class:`~stride_jax.gap.effects.Plan`, its ``MjModel`` as MuJoCo serialises it), the replaying
:class:`~stride_jax.sim.model.SimModel`'s model and control structure, the number of periods,
the windows (``start``, ``first``), their initial states and the logged commands. Results are
stored read-only (a caller that wrote into one would corrupt later hits; it fails instead) and
evicted least recently used past ``STRIDE_GAP_MEMO_MB`` megabytes (default 256; 0 turns the memo
off). :func:`stats` counts hits and misses. Each entry keeps how many of its worlds diverged, and a
hit counts them again in :func:`stride_jax.gap.sim.unstable` (as the replay it stands for would:
the fits skip finite-difference points whose replay diverged, and must decide alike); MuJoCo's
warnings are not repeated.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import threading
from collections import OrderedDict

import mujoco
import numpy as np

_LOCK = threading.Lock()
_STORE: OrderedDict[bytes, tuple[np.ndarray, np.ndarray, int]] = OrderedDict()
_STATS = {"hits": 0, "misses": 0, "bytes": 0}


def limit_bytes() -> int:
    """The memo's size limit (``STRIDE_GAP_MEMO_MB``, megabytes; 0: off)."""
    raw = os.environ.get("STRIDE_GAP_MEMO_MB", "256")
    try:
        mb = float(raw)
    except ValueError:
        raise ValueError(f"STRIDE_GAP_MEMO_MB={raw!r} is not a number of megabytes") from None
    if mb < 0:
        raise ValueError(f"STRIDE_GAP_MEMO_MB={raw!r} must be >= 0 (0: no memo)")
    return int(mb * 2 ** 20)


def _model_bytes(m: mujoco.MjModel) -> bytes:
    buf = np.empty(mujoco.mj_sizeModel(m), np.uint8)
    mujoco.mj_saveModel(m, None, buf)
    return buf.tobytes()


def _feed(h, value) -> None:
    if isinstance(value, mujoco.MjModel):
        h.update(b"M")
        h.update(_model_bytes(value))
    elif isinstance(value, np.ndarray):
        a = np.ascontiguousarray(value)
        h.update(f"A{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
    elif value is None:
        h.update(b"N")
    elif isinstance(value, (bool, int, float, str)):
        h.update(f"{type(value).__name__}:{value!r}".encode())
    else:
        raise TypeError(f"memo: cannot key a value of type {type(value).__name__}")


def plan_key(plan) -> bytes:
    """A digest of every field of a :class:`~stride_jax.gap.effects.Plan` (a field added later is
    keyed too; one of a type this cannot digest is an error, not a silent collision)."""
    h = hashlib.blake2b(digest_size=20)
    for f in dataclasses.fields(plan):
        h.update(f.name.encode())
        _feed(h, getattr(plan, f.name))
    return h.digest()


def windows_key(sm, q: np.ndarray, qd: np.ndarray, cmd: np.ndarray, start: np.ndarray, first: np.ndarray,
                k: int) -> bytes:
    """A digest of what a replay reads besides its plan: ``sm``'s model and control structure,
    ``k``, the windows and their initial states, and the logged commands."""
    start, first = np.asarray(start, np.int64), np.asarray(first, np.int64)  # one key whatever int type
    h = hashlib.blake2b(digest_size=20)
    for v in (sm.mj, int(sm.n_substeps), sm.robot.kp is None, np.asarray(sm.act_dof), int(sm.base_body), int(k),
              start, first, np.asarray(q)[start], np.asarray(qd)[start], np.asarray(cmd)):
        _feed(h, v)
    return h.digest()


def get(key: bytes) -> tuple[np.ndarray, np.ndarray, int] | None:
    """The stored ``(q, qd, diverged)`` of a replay, or None (counted as a miss)."""
    with _LOCK:
        hit = _STORE.get(key)
        if hit is None:
            _STATS["misses"] += 1
            return None
        _STORE.move_to_end(key)
        _STATS["hits"] += 1
        return hit


def put(key: bytes, q: np.ndarray, qd: np.ndarray, diverged: int) -> tuple[np.ndarray, np.ndarray]:
    """Stores a replay's ``(q, qd)`` (copies, read-only) with the count of its worlds that
    diverged, and returns the copies."""
    limit = limit_bytes()
    q, qd = np.array(q), np.array(qd)
    q.setflags(write=False)
    qd.setflags(write=False)
    size = q.nbytes + qd.nbytes
    if limit == 0 or size > limit:
        return q, qd
    with _LOCK:
        if key not in _STORE:
            _STORE[key] = (q, qd, int(diverged))
            _STATS["bytes"] += size
        while _STATS["bytes"] > limit:
            _, (a, b, _n) = _STORE.popitem(last=False)
            _STATS["bytes"] -= a.nbytes + b.nbytes
    return q, qd


def enabled() -> bool:
    return limit_bytes() > 0


def clear() -> None:
    """Forgets every stored replay (the counts too)."""
    with _LOCK:
        _STORE.clear()
        _STATS.update(hits=0, misses=0, bytes=0)


def stats() -> dict[str, int]:
    """Running totals since import or :func:`clear`: ``hits``, ``misses`` and the ``bytes`` held."""
    with _LOCK:
        return dict(_STATS)
