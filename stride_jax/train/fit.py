"""Training on a robot given only as arrays: no MJCF, no registered name.

    model, params = stride_jax.train.fit(q, qd, tau, qdd, "runs/my_arm")

fits DeLaN's Lagrangian prior (or any structured model of ``dynamics.MODELS``) to samples of a
fixed-base robot's inverse dynamics ``tau = M(q) qdd + C(q, qd) qd + g(q)`` with the loop of
``stride train``, and leaves a run folder that ``stride_jax.dynamics.load`` reads.
"""

from __future__ import annotations

import pathlib
from typing import Callable

import jax
import numpy as np

from stride_jax.dynamics import checkpoint, models, stride
from stride_jax.train import dynamics, loop, setup
from stride_jax.types import ModelSpec


def fit(q, qd, tau, qdd, out: str | pathlib.Path, model: str = "delan_prior",
        periodic: tuple[bool, ...] = (),
        config: stride.StructuredConfig = stride.StructuredConfig(),
        loop_cfg: loop.LoopConfig = loop.LoopConfig(), val_fraction: float = 0.1,
        dt: float = 0.01, log: Callable[[str], None] = print) -> tuple[models.Model, dict]:
    """Trains ``model`` on samples ``q, qd, tau, qdd`` ``[N, n]`` (rad, rad/s, N m, rad/s^2) of
    a fixed-base robot with ``n`` joints driven by motors (``tau`` is the joint torque) and
    returns ``(model, best params)``.

    ``periodic``: per joint, whether it wraps around (fed to the networks as sin, cos).
    ``config``: network sizes and loss settings; ``loop_cfg``: steps, batch, learning rate and
    seed. A random ``val_fraction`` of the samples is held out to pick the best parameters.
    ``out`` is the run folder (resumable; ``dynamics.load(out)`` restores the result). ``dt``:
    the control period of the returned model's ``step`` (s).

    The default ``delan_prior`` is DeLaN as published: the prior alone, trained on the
    acceleration error. Arrays are used in JAX's default float precision (float64 with
    ``jax_enable_x64``, where the float32 parameters are promoted in every computation).
    """
    family = models.MODELS.get(model, (None,))[0]
    if family != "structured":
        names = ", ".join(k for k, v in models.MODELS.items() if v[0] == "structured")
        raise ValueError(f"fit trains the structured models ({names}), not {model!r}")
    dtype = jax.dtypes.canonicalize_dtype(np.float64)
    arrays = {k: np.asarray(x, dtype) for k, x in dict(q=q, qd=qd, tau=tau, qdd=qdd).items()}
    n, nq = arrays["q"].shape if arrays["q"].ndim == 2 else (None, None)
    for k, x in arrays.items():
        if x.ndim != 2 or x.shape != (n, nq):
            raise ValueError(f"fit: {k} must have shape [N, n] like q {arrays['q'].shape}, got "
                             f"{x.shape}")
        if not np.isfinite(x).all():
            raise ValueError(f"fit: {k} holds NaN or inf values")
    spec = ModelSpec(nq=nq, nv=nq, floating_base=False, periodic=tuple(periodic))
    perm = np.random.default_rng(loop_cfg.seed).permutation(n)
    n_val = max(1, int(round(val_fraction * n)))
    if n - n_val < 1:
        raise ValueError(f"fit: {n} samples leave none for training")
    train = {k: x[perm[n_val:]] for k, x in arrays.items()}
    val = {k: x[perm[:n_val]] for k, x in arrays.items()}

    std = lambda x: setup.floored_std(x, dtype)  # noqa: E731  (as for simulated datasets)
    scales = stride.Scales(qd=std(train["qd"]), tau=std(train["tau"]), force=std(train["tau"]),
                           qdd=std(train["qdd"]))
    m = models.make(model, spec, models.motors(nq, dt), config, scales)
    out = pathlib.Path(out)
    out.mkdir(parents=True, exist_ok=True)
    checkpoint.save_definition(out, m)
    params = dynamics.train_examples(m.loss, m.init, train, val, loop_cfg, out, log)
    return m, params
