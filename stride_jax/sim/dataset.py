"""Datasets on disk: one folder per dataset, ``arrays.npz`` plus ``meta.json``.

``arrays.npz`` holds every :class:`~stride_jax.sim.record.Record` field as ``[E, T, ...]``
(episodes x control steps), ``valid`` ``[E, T]``, and the hidden per-episode values as
``rand/<name>`` and ``explore/<name>`` ``[E, ...]`` (for analysis only: models must not read
them). ``meta.json`` holds the robot, timing, seed, exploration, randomisation ranges, package
versions, the split of episodes into train/val/test, normalisation statistics of the training
split, and the array file's size and SHA-256. Both files are written atomically (temporary file,
then ``os.replace``), so an interrupted write never leaves a half-written dataset behind.
"""

from __future__ import annotations

import dataclasses
import json
import os
import pathlib
import zipfile
from importlib import metadata
from typing import Any

import numpy as np

from stride_jax import io
from stride_jax.sim import record
from stride_jax.sim.rollout_mjx import Episode

FORMAT_VERSION = 1
NORMALISED = ("q", "qd", "qdd", "ctrl", "tau", "qfrc_passive", "qfrc_constraint", "foot_force")


class DatasetError(ValueError):
    """A dataset that is missing, corrupt, or does not match what was asked for."""


@dataclasses.dataclass(frozen=True)
class Dataset:
    """A loaded dataset. ``arrays`` maps field names to numpy arrays; ``meta`` is the JSON dict."""

    path: pathlib.Path
    arrays: dict[str, np.ndarray]
    meta: dict[str, Any]

    def split(self, name: str) -> dict[str, np.ndarray]:
        """The arrays of the ``train``, ``val`` or ``test`` episodes."""
        if name not in self.meta["splits"]:
            raise DatasetError(f"{self.path}: no split {name!r}; have {list(self.meta['splits'])}")
        idx = np.asarray(self.meta["splits"][name], dtype=np.int64)
        return {k: v[idx] for k, v in self.arrays.items()}

    @property
    def stats(self) -> dict[str, dict[str, np.ndarray]]:
        """Per-field ``mean``/``std`` over the valid steps of the training split."""
        return {k: {s: np.asarray(v) for s, v in st.items()} for k, st in self.meta["stats"].items()}


def _versions() -> dict[str, str]:
    out = {}
    for pkg in ("stride_jax", "jax", "mujoco", "mujoco-mjx", "numpy"):
        try:
            out[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            out[pkg] = "not installed"
    return out


def split_episodes(n: int, seed: int, fractions=(0.8, 0.1, 0.1)) -> dict[str, list[int]]:
    """Random split of whole episodes (trajectories never straddle splits)."""
    if n < 3:
        raise DatasetError(f"need at least 3 episodes to split into train/val/test, got {n}")
    perm = np.random.default_rng(seed).permutation(n)
    n_val = max(1, int(round(fractions[1] * n)))
    n_test = max(1, int(round(fractions[2] * n)))
    n_train = n - n_val - n_test
    return {"train": sorted(perm[:n_train].tolist()),
            "val": sorted(perm[n_train:n_train + n_val].tolist()),
            "test": sorted(perm[n_train + n_val:].tolist())}


def statistics(arrays: dict[str, np.ndarray], episodes: list[int]) -> dict[str, dict[str, list]]:
    """Mean and std (floored at 1e-6) of the normalised fields over valid training steps."""
    valid = arrays["valid"][episodes]
    if not valid.any():
        raise DatasetError("the training split has no valid steps (every episode fell at once?)")
    out = {}
    for k in NORMALISED:
        x = arrays[k][episodes][valid].astype(np.float64)
        out[k] = {"mean": x.mean(0).tolist(), "std": np.maximum(x.std(0), 1e-6).tolist()}
    return out


def episode_arrays(ep: Episode) -> dict[str, np.ndarray]:
    """Flattens an :class:`Episode` into the named arrays stored in ``arrays.npz``."""
    arrays = {f: np.asarray(getattr(ep.records, f)) for f in record.FIELDS}
    # A step is valid only if everything recorded at it is finite, and stays invalid from the
    # first bad step on (the backends check the state; an unconverged solve can still return a
    # non-finite acceleration or force while the state is finite -- seen on GPU with MJX).
    finite = np.ones(np.shape(ep.valid), bool)
    for f in record.FIELDS:
        x = arrays[f]
        if x.dtype.kind == "f":
            finite &= np.isfinite(x).reshape(*finite.shape, -1).all(-1)
    arrays["valid"] = np.asarray(ep.valid, bool) & np.logical_and.accumulate(finite, axis=1)
    for name, v in ep.rand._asdict().items():
        arrays[f"rand/{name}"] = np.asarray(v)
    explore = ep.explore._asdict() if hasattr(ep.explore, "_asdict") else {}
    for name, v in explore.items():
        arrays[f"explore/{name}"] = np.asarray(v)
    for k, v in arrays.items():
        if v.dtype.kind == "f":
            arrays[k] = v.astype(np.float32)
    return arrays


def save(path: str | os.PathLike, ep: Episode, meta: dict[str, Any]) -> Dataset:
    """Writes a dataset folder atomically; ``meta`` must name at least ``robot``, ``dt``, ``seed``.

    Splits, statistics, versions, sizes and checksums are added here.
    """
    path = pathlib.Path(path)
    path.mkdir(parents=True, exist_ok=True)
    arrays = episode_arrays(ep)
    n = arrays["valid"].shape[0]
    meta = dict(meta)
    meta.setdefault("seed", 0)
    meta["format_version"] = FORMAT_VERSION
    meta["versions"] = _versions()
    meta["n_episodes"], meta["n_steps"] = n, int(arrays["valid"].shape[1])
    meta["valid_fraction"] = float(arrays["valid"].mean())
    meta["splits"] = split_episodes(n, meta["seed"])
    meta["stats"] = statistics(arrays, meta["splits"]["train"])
    meta["fields"] = {k: [list(v.shape), str(v.dtype)] for k, v in arrays.items()}
    arrays_path = path / "arrays.npz"
    io.atomic_write(arrays_path, lambda f: np.savez(f, **arrays))
    meta["arrays_bytes"] = arrays_path.stat().st_size
    meta["arrays_sha256"] = io.file_sha256(arrays_path)
    io.atomic_write(path / "meta.json", lambda f: f.write(json.dumps(meta, indent=1).encode()))
    return Dataset(path, arrays, meta)


def load(path: str | os.PathLike, robot: str | None = None, verify: bool = True) -> Dataset:
    """Loads a dataset folder; clear errors for missing, truncated, corrupt or mismatched data."""
    path = pathlib.Path(path)
    meta_path, arrays_path = path / "meta.json", path / "arrays.npz"
    for p in (meta_path, arrays_path):
        if not p.is_file():
            raise DatasetError(f"dataset {path}: missing {p.name} (make one with `stride data`)")
    try:
        meta = json.loads(meta_path.read_text())
    except json.JSONDecodeError as e:
        raise DatasetError(f"dataset {path}: meta.json is not valid JSON ({e})") from e
    if meta.get("format_version") != FORMAT_VERSION:
        raise DatasetError(f"dataset {path}: format version {meta.get('format_version')}, this "
                           f"stride_jax reads version {FORMAT_VERSION}")
    if robot is not None and meta.get("robot") != robot:
        raise DatasetError(f"dataset {path} holds robot {meta.get('robot')!r}, not {robot!r}")
    size = arrays_path.stat().st_size
    if size != meta["arrays_bytes"]:
        raise DatasetError(f"dataset {path}: arrays.npz has {size} bytes, meta.json recorded "
                           f"{meta['arrays_bytes']} (truncated or replaced file)")
    if verify and io.file_sha256(arrays_path) != meta["arrays_sha256"]:
        raise DatasetError(f"dataset {path}: arrays.npz fails its SHA-256 check (corrupt file)")
    try:
        with np.load(arrays_path) as z:
            arrays = {k: z[k] for k in z.files}
    except (zipfile.BadZipFile, ValueError, OSError, EOFError) as e:
        raise DatasetError(f"dataset {path}: cannot read arrays.npz ({e})") from e
    for k, (shape, dtype) in meta["fields"].items():
        if k not in arrays or list(arrays[k].shape) != shape or str(arrays[k].dtype) != dtype:
            raise DatasetError(f"dataset {path}: field {k!r} does not match meta.json "
                               f"(expected {shape} {dtype})")
    return Dataset(path, arrays, meta)
