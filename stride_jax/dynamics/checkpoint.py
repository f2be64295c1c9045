"""Saving and loading models: a folder holds ``model.json`` (what the model is: coordinates,
actuation, config, normalisers) and its parameters, each with a SHA-256 checksum.

Two kinds of folder load the same way, with :func:`load` and nothing else:

* a **saved model** (:func:`save`): ``model.json`` names ``params.npz`` and its checksum;
* a **training run** (``stride train``, :func:`stride_jax.train.fit`): ``model.json`` beside
  orbax checkpoints in ``best/``, whose checksum the training loop records in ``summary.json``.

A damaged folder is refused with :class:`CheckpointError` naming the file: changed parameter
bytes (a checksum mismatch), non-finite parameters, a ``model.json`` that is not valid JSON or
does not describe a model. Runs written before checksums existed load without the check.
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import json
import pathlib
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from stride_jax.dynamics import mlp, stride
from stride_jax.dynamics.models import Actuation, Model, make
from stride_jax.io import atomic_write, atomic_write_text
from stride_jax.types import ModelSpec

PARAMS_FILE = "params.npz"


class CheckpointError(ValueError):
    """A saved model or training run cannot be loaded as it is: damaged or incomplete."""


def params_sha256(params: Any) -> str:
    """SHA-256 of a params pytree: every leaf's path, dtype, shape and bytes (C order), leaves
    sorted by path, so the digest depends on the values and not on how they were stored."""
    leaves = jax.tree_util.tree_flatten_with_path(params)[0]
    digest = hashlib.sha256()
    for path, leaf in sorted((jax.tree_util.keystr(p), x) for p, x in leaves):
        a = np.ascontiguousarray(np.asarray(leaf))
        digest.update(f"{path}|{a.dtype.str}|{a.shape}\n".encode())
        digest.update(a.tobytes())
    return digest.hexdigest()


def definition(model: Model) -> dict:
    """What ``model.json`` holds about ``model``, as plain JSON values."""
    if model.spec is None or model.config is None:
        raise ValueError(f"model {model.name!r} does not carry its definition; build it with "
                         "stride_jax.dynamics.make")
    as_list = lambda x: np.asarray(x, np.float64).reshape(-1).tolist()  # noqa: E731
    return {"name": model.name, "spec": dataclasses.asdict(model.spec),
            "actuation": dataclasses.asdict(model.actuation),
            "config": dataclasses.asdict(model.config),
            "scales": {k: as_list(v) for k, v in model.scales._asdict().items()}}


def program_sha256(model: Model) -> str:
    """The checksum of ``model``'s definition with its data scales reduced to their shapes: two
    models with the same one compute the same function of ``(params, scales)``
    (:func:`with_scales`), so a program traced for one runs the other. Trained seeds of one
    recipe differ in their scales' last bits (statistics reduced in another order on a GPU),
    so the checksums of their definitions (``model.json``'s ``definition_sha256``) differ while
    this one does not."""
    d = definition(model)
    d["scales"] = {k: len(v) for k, v in d["scales"].items()}
    return _digest(d)


def with_scales(model: Model, scales: stride.Scales) -> Model:
    """``model`` with other data scales (traced arrays too: a compiled program takes them as an
    argument beside the parameters, :func:`program_sha256`)."""
    if model.scales is None or jax.tree.structure(scales) != jax.tree.structure(model.scales):
        raise ValueError(f"scales of model {model.name!r} must be a stride.Scales")
    return make(model.name, model.spec, model.actuation, model.config, scales)


def _digest(d: dict) -> str:
    body = {k: v for k, v in d.items() if k not in ("definition_sha256", "params")}
    return hashlib.sha256(json.dumps(body, sort_keys=True).encode()).hexdigest()


def save_definition(folder: str | pathlib.Path, model: Model, params_entry: dict | None = None
                    ) -> None:
    """Writes ``folder/model.json`` (atomically) with the checksum of its own contents;
    ``params_entry`` (``{"file", "sha256"}``) names a saved model's parameters."""
    d = definition(model)
    d["definition_sha256"] = _digest(d)
    if params_entry is not None:
        d["params"] = params_entry
    atomic_write_text(pathlib.Path(folder) / "model.json", json.dumps(d, indent=1))


def save(folder: str | pathlib.Path, model: Model, params: Any) -> pathlib.Path:
    """Saves ``model`` and ``params`` into ``folder`` (created): ``params.npz`` then
    ``model.json`` with both checksums, each written atomically. :func:`load` restores them."""
    folder = pathlib.Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    want = jax.tree.structure(jax.eval_shape(model.init, jax.random.key(0)))
    if jax.tree.structure(params) != want:
        raise ValueError(f"params do not belong to model {model.name!r}: pytree {want} expected")
    leaves = [np.asarray(x) for x in jax.tree.leaves(params)]
    if not all(np.isfinite(x).all() for x in leaves):
        raise ValueError("params hold NaN or inf values; not saving them")

    def write(f):
        buf = io.BytesIO()
        np.savez(buf, **{f"{i:05d}": x for i, x in enumerate(leaves)})
        f.write(buf.getvalue())

    atomic_write(folder / PARAMS_FILE, write)
    save_definition(folder, model, {"file": PARAMS_FILE, "sha256": params_sha256(params)})
    return folder


def read_json(path: pathlib.Path) -> dict:
    """A JSON object from ``path``, or a :class:`CheckpointError` naming the file."""
    try:
        d = json.loads(path.read_bytes().decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise CheckpointError(f"{path} is damaged: not valid UTF-8 JSON ({e})") from e
    if not isinstance(d, dict):
        raise CheckpointError(f"{path} is damaged: a JSON object expected, got "
                              f"{type(d).__name__}")
    return d


def model_from_definition(d: dict, kernel: str | None = None) -> Model:
    """The model a ``model.json`` describes; ``kernel`` overrides how its networks run at
    inference (``StructuredConfig.kernel``). Fills in what older runs did not record."""
    spec = ModelSpec(**{k: tuple(v) if isinstance(v, list) else v for k, v in d["spec"].items()})
    act = Actuation.from_dict(d["actuation"])
    c = dict(d["config"])
    c.setdefault("learn_mass", True)  # runs defined before the option learned their mass
    c.setdefault("base_structure", True)  # runs defined before the switch had the structure
    # Runs defined before v-prediction: noise prediction on a schedule ending at 1e-5, clipped
    # at 10; their acceleration loss trained the prior only.
    for k, v in dict(diffusion_target="eps", abar_min=1e-5, diffusion_clip=10.0,
                     acc_through="prior").items():
        c.setdefault(k, v)
    cfg = stride.StructuredConfig(**dict(c, net=mlp.MLPConfig(**c["net"])))
    if kernel is not None:
        cfg = dataclasses.replace(cfg, kernel=kernel)
    sc = stride.Scales(**{k: jnp.asarray(v, jnp.float32) for k, v in d["scales"].items()})
    return make(d["name"], spec, act, cfg, sc)


def load(folder: str | pathlib.Path, kernel: str | None = None) -> tuple[Model, Any]:
    """``(model, params)`` from a folder of :func:`save` or a training run (its best, lowest
    validation loss, parameters); ``kernel`` overrides how its networks run at inference
    (``StructuredConfig.kernel``). Raises :class:`CheckpointError` on a damaged folder."""
    folder = pathlib.Path(folder)
    path = folder / "model.json"
    if not path.is_file():
        raise FileNotFoundError(f"{folder} is neither a saved model nor a training run (no "
                                "model.json); save one with stride_jax.dynamics.save or train "
                                "one with `stride train`")
    d = read_json(path)
    if "definition_sha256" in d and d["definition_sha256"] != _digest(d):
        raise CheckpointError(f"{path} is damaged: its contents do not match their checksum")
    try:
        model = model_from_definition(d, kernel)
    except (KeyError, TypeError, ValueError) as e:
        raise CheckpointError(f"{path} does not describe a model ({type(e).__name__}: {e})"
                              ) from e
    if "params" in d:
        params, where, expected = _read_npz(folder, model, d["params"])
    else:
        params, where, expected = _read_run(folder, model)
    if expected is not None and params_sha256(params) != expected:
        raise CheckpointError(f"{where} is damaged: its parameters do not match the checksum "
                              "recorded when they were saved")
    bad = sum(int((~np.isfinite(np.asarray(x))).sum()) for x in jax.tree.leaves(params))
    if bad:
        raise CheckpointError(f"{where} is damaged: {bad} parameters are NaN or inf")
    return model, params


def _read_npz(folder: pathlib.Path, model: Model, entry: dict) -> tuple[Any, pathlib.Path, str]:
    path = folder / entry["file"]
    if not path.is_file():
        raise CheckpointError(f"{path} is missing (named by {folder / 'model.json'})")
    target = jax.eval_shape(model.init, jax.random.key(0))
    shapes, treedef = jax.tree.flatten(target)
    try:
        with np.load(path, allow_pickle=False) as f:
            leaves = [f[f"{i:05d}"] for i in range(len(shapes))]
    except Exception as e:  # noqa: BLE001 -- zip, zlib and key errors all mean a damaged file
        raise CheckpointError(f"{path} is damaged: cannot read it ({type(e).__name__}: {e})"
                              ) from e
    for x, s in zip(leaves, shapes, strict=True):  # float64 params (a user's cast) stay so
        if x.shape != s.shape or x.dtype.kind != np.dtype(s.dtype).kind:
            raise CheckpointError(f"{path} does not fit the model of model.json: "
                                  f"{x.dtype}{list(x.shape)} where {s.dtype}{list(s.shape)}")
    return jax.tree.unflatten(treedef, [jnp.asarray(x) for x in leaves]), path, entry["sha256"]


def _read_run(folder: pathlib.Path, model: Model) -> tuple[Any, pathlib.Path, str | None]:
    """The best parameters of a training run and the checksum its summary records (none for
    runs written before checksums)."""
    import orbax.checkpoint as ocp

    mngr = ocp.CheckpointManager((folder / "best").absolute())
    step = mngr.latest_step()
    # The step the run's summary names, where it has one: a copied run folder may carry stale
    # checkpoints beside it (a later step of an older model, say).
    summary = read_json(folder / "summary.json") if (folder / "summary.json").is_file() else {}
    named = summary.get("best_step")
    if named in mngr.all_steps():
        step = named
    if step is None:
        raise FileNotFoundError(f"{folder / 'best'} holds no checkpoint")
    target = model.init(jax.random.key(0))
    where = folder / "best" / str(step)
    try:
        params = mngr.restore(step, args=ocp.args.StandardRestore(target))
    except Exception as e:  # noqa: BLE001 -- orbax, tensorstore and codec errors alike
        raise CheckpointError(f"{where} is damaged: cannot restore it ({type(e).__name__}: {e})"
                              ) from e
    expected = summary.get("params_sha256") if step == named else None
    return params, where, expected
