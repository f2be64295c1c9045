"""The sizes of every model on every robot -> docs/models.md (``python experiments/sizes.py``).

All models share one network size (``--hidden`` x ``--depth``, SiLU); what differs is how many
networks a model has and what they read and write.
"""

from __future__ import annotations

import argparse
import pathlib
import sys

import jax

import stride_jax
from stride_jax.dynamics import models, stride
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


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--hidden", type=int, default=256)
    p.add_argument("--depth", type=int, default=3)
    p.add_argument("--robots", default="pendulum,go1,g1")
    p.add_argument("--out", default="docs/models.md")
    args = p.parse_args(argv)
    robots = args.robots.split(",")
    rows = []
    for name in models.MODELS:
        counts = []
        for robot in robots:
            meta = sim_model.robot_meta(sim_model.load(robot))
            cfg = model_config(name, meta, args.hidden, args.depth)
            model = models.make(name, models.spec_from_meta(meta), models.Actuation.from_meta(meta),
                                cfg, stride.Scales())
            params = model.init(jax.random.key(0))
            counts.append(sum(x.size for x in jax.tree.leaves(params)))
        nfe = models.DEFAULT_NFE.get(models.MODELS[name][1])
        rows.append(f"| {name} | {NETWORKS[name]} | {nfe or '-'} | "
                    + " | ".join(f"{c:,}" for c in counts) + " |")
    command = "python experiments/sizes.py " + " ".join(sys.argv[1:] if argv is None else argv)
    text = "\n".join([
        "# Model sizes", "",
        f"Made by `{command.strip()}`. Every network: {args.hidden} hidden units x {args.depth} "
        "layers, SiLU, the same for all models (the paper's \"same size\"); every model trains "
        "for the same steps with the same optimiser (`stride_jax/jobs/train.py` presets).", "",
        "| model | networks | default NFE | " + " | ".join(f"params ({r})" for r in robots)
        + " |", "|---|---|---|" + "---|" * len(robots), *rows, ""])
    path = pathlib.Path(args.out)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, text)
    print(text)


if __name__ == "__main__":
    stride_jax.set_xla_flags()  # before JAX starts: small CPUs deadlock without
    main()
