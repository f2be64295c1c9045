"""Which robot and network sizes the whole-step kernel (``pallas-step``) compiles for on this GPU:
Triton keeps a program's weight tiles in shared memory, which is bounded per SM (227 KiB on an
H100). Prints one line per case; ``models.whole_step_fits`` takes its size rule from this.

    python experiments/probes/fused_step_smem.py [--robots go1,g1] [--hidden 32,64,128,256]

Each robot is the registered one (Go1: 12 servo joints, G1: 29), its model at initialisation;
only compiling is timed, so the states are the home pose.
"""

from __future__ import annotations

import argparse
import json
import re

import jax
import jax.numpy as jnp

import stride_jax
from stride_jax.dynamics import fused_layout, mlp, models, stride
from stride_jax.sim import model as sim_model


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--robots", default="go1,g1")
    p.add_argument("--hidden", default="32,64,128,256")
    p.add_argument("--depth", type=int, default=3)
    p.add_argument("--samples", type=int, default=64)
    args = p.parse_args(argv)
    for robot in args.robots.split(","):
        sm = sim_model.load(robot)
        meta = sim_model.robot_meta(sm)
        spec, act = models.spec_from_meta(meta), models.Actuation.from_meta(meta)
        lay = fused_layout.Layout.of(spec.nv, act.dof)
        n = args.samples
        q = jnp.tile(jnp.asarray(sm.info.qpos0, jnp.float32), (n, 1))
        qd = jnp.zeros((n, spec.nv))
        ctrl = jnp.tile(jnp.asarray(sm.info.qpos0[spec.nq - len(act.dof):], jnp.float32), (n, 1))
        keys = jax.random.split(jax.random.key(0), n)
        for h in map(int, args.hidden.split(",")):
            cfg = stride.StructuredConfig(net=mlp.MLPConfig(hidden=h, depth=args.depth),
                                          shared_lnn=True, kernel="pallas-step")
            m = models.make("stride", spec, act, cfg)
            params = m.init(jax.random.key(0))
            row = dict(robot=robot, joints=len(act.dof), nv=spec.nv, entries=lay.entries, hidden=h)
            try:
                jax.jit(jax.vmap(lambda *a: m.step(params, *a))).lower(
                    q, qd, ctrl, keys).compile()
                row["compiles"] = True
            except Exception as e:  # noqa: BLE001 -- report whatever the compiler says
                msg = str(e)
                got = re.search(r"requested (\d+), available: (\d+)", msg)
                row.update(compiles=False, error=msg.splitlines()[0][:160])
                if got:
                    row.update(smem_requested=int(got[1]), smem_available=int(got[2]))
            print(json.dumps(row), flush=True)


if __name__ == "__main__":
    stride_jax.set_xla_flags()  # before JAX starts: small CPUs deadlock without
    main()
