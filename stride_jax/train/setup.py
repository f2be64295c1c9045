"""What a model trained on a dataset starts from: its config (network sizes, the residual's
evaluations, the starting total mass) and its normalisers (per-dof scales of the training split).

Used by ``stride train`` (:mod:`stride_jax.jobs.train`), the MPPI benchmark and the gap tool's
residual, and, for the scales' floor, by :func:`stride_jax.train.fit` on a user's arrays.
"""

from __future__ import annotations

import numpy as np

from stride_jax.dynamics import integrate, mlp, models, stride
from stride_jax.sim import dataset
from stride_jax.sim import model as sim_model


def model_config(model: str, meta: dict, hidden: int, depth: int, nfe: int = 0,
                 shared_lnn: bool = False, acc_through: str = "central",
                 learn_mass: bool = False, activation: str = "silu",
                 weight_init: str = "lecun_normal", base_structure: bool = True,
                 transition_weight: float = 0.0,
                 transition_fraction: float = 1.0, potential: str = "net",
                 gravity_context: bool = False, base_weight: float = 1.0) -> stride.StructuredConfig:
    """Sizes for ``model`` on the robot ``meta`` describes (a dataset's ``meta.json`` or
    :func:`stride_jax.sim.model.robot_meta`); ``nfe=0`` takes its default. Floating bases start
    the learned total mass at the nominal model's (a spec-sheet number); ``base_structure=False``
    drops the floating-base structure (``LNNConfig.base_structure``, an ablation);
    ``transition_weight`` adds the one-control-period transition loss (structured models), on
    ``transition_fraction`` of each minibatch; ``potential``: the prior's potential
    (``LNNConfig.potential``); ``gravity_context``: the networks see gravity's direction
    (``StructuredConfig.gravity_context``, for sloped data); ``base_weight``: a floating base's
    dofs' weight in the one-period losses (``StructuredConfig.base_weight``)."""
    models.check_name(model)
    nfe = nfe or models.DEFAULT_NFE.get(models.MODELS[model][1], 2)
    mass = meta.get("total_mass") or float(sim_model.load(meta["robot"]).mj.body_mass.sum())
    return stride.StructuredConfig(net=mlp.MLPConfig(hidden, depth, activation, weight_init),
                                   nfe=nfe,
                                   mass_init=mass if meta["floating_base"] else 1.0,
                                   shared_lnn=shared_lnn, acc_through=acc_through,
                                   learn_mass=learn_mass, base_structure=base_structure,
                                   transition_weight=transition_weight,
                                   transition_fraction=transition_fraction,
                                   potential=potential, gravity_context=gravity_context,
                                   base_weight=base_weight)


def floored_std(x: np.ndarray, dtype=np.float32) -> np.ndarray:
    """Per-column std of ``x`` ``[N, n]``, floored at 1% of the largest (and at 1e-5), so that a
    dof that barely moves does not blow its normalised values up."""
    s = x.std(0)
    return np.maximum(s, 1e-2 * max(float(s.max()), 1e-3)).astype(dtype)


def scales(ds: dataset.Dataset) -> stride.Scales:
    """Per-dof normalisers from the training split's valid steps."""
    train = ds.split("train")
    v = train["valid"]
    force = (train["qfrc_passive"] + train["qfrc_constraint"] + train["qfrc_external"])[v]
    dq, dqd = integrate.one_step_changes(train, ds.meta["floating_base"])
    std = floored_std
    return stride.Scales(qd=std(train["qd"][v]), tau=std(train["tau"][v]), force=std(force),
                         qdd=std(train["qdd"][v]), dq=std(dq), dqd=std(dqd),
                         ctrl=std(train["ctrl"][v]))
