"""The sizes of every model on every robot -> docs/models.md (``python experiments/sizes.py``).

All models share one network size (``--net.hidden`` x ``--net.depth``, the library's
:class:`~stride_jax.dynamics.mlp.MLPConfig`); what differs is how many networks a model has and
what they read and write.
"""

from __future__ import annotations

import dataclasses
import pathlib

import jax

import stride_jax
from stride_jax import config
from stride_jax.dynamics import mlp, models, stride
from stride_jax.io import atomic_write_text
from stride_jax.sim import model as sim_model
from stride_jax.train.setup import model_config

NETWORKS = {
    "stride": "L(q) Cholesky net, V(q) net, flow field v(z, t; q, qd, tau)",
    "delan": "L(q) Cholesky net, V(q) net, residual MLP r(q, qd, tau)",
    "delan_prior": "L(q) Cholesky net, V(q) net (DeLaN as published: no residual)",
    "lnn_diffusion": "L(q) Cholesky net, V(q) net, DDPM noise net e(x, s; q, qd, tau)",
    "onn": "one MLP (q, qd, ctrl) -> change of (q, qd)",
    "diffusion": "one DDPM noise net e(x, s; q, qd, ctrl) over the change of (q, qd)",
}


@dataclasses.dataclass(frozen=True)
class SizesConfig:
    """What the sizes page counts.

    Attributes:
      net: every model's networks (one size for all models).
      robots: comma-separated robots, one column each.
      out: the page written.
    """

    net: mlp.MLPConfig = mlp.MLPConfig()
    robots: str = "pendulum,go1,g1"
    out: str = "docs/models.md"


PRESETS = {"default": SizesConfig()}


def run(cfg: SizesConfig, command: str, log=print) -> None:
    net, robots = cfg.net, cfg.robots.split(",")
    rows = []
    for name in models.MODELS:
        counts = []
        for robot in robots:
            meta = sim_model.robot_meta(sim_model.load(robot))
            model_cfg = model_config(name, meta, net.hidden, net.depth, activation=net.activation,
                                     weight_init=net.init)
            model = models.make(name, models.spec_from_meta(meta), models.Actuation.from_meta(meta),
                                model_cfg, stride.Scales())
            params = model.init(jax.random.key(0))
            counts.append(sum(x.size for x in jax.tree.leaves(params)))
        nfe = models.DEFAULT_NFE.get(models.MODELS[name][1])
        rows.append(f"| {name} | {NETWORKS[name]} | {nfe or '-'} | "
                    + " | ".join(f"{c:,}" for c in counts) + " |")
    activation = "SiLU" if net.activation == "silu" else net.activation
    text = "\n".join([
        "# Model sizes", "",
        f"Made by `{command}`. Every network: {net.hidden} hidden units x {net.depth} layers, "
        f"{activation}, the same for all models (the paper's \"same size\"); every model trains "
        "for the same steps with the same optimiser (`stride_jax/jobs/train.py` presets).", "",
        "| model | networks | default NFE | " + " | ".join(f"params ({r})" for r in robots)
        + " |", "|---|---|---|" + "---|" * len(robots), *rows, ""])
    path = pathlib.Path(cfg.out)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, text)
    log(text)


if __name__ == "__main__":
    stride_jax.set_xla_flags()  # before JAX starts: small CPUs deadlock without
    config.config_main("python experiments/sizes.py", SizesConfig, PRESETS, run,
                       description=__doc__)
