"""Which robot and network sizes the whole-step kernel (``pallas-step``) compiles for on this GPU:
Triton keeps a program's weight tiles in shared memory, which is bounded per SM (227 KiB on an
H100). Prints one line per case; ``models._whole_step_applies`` takes its size rule from this.

    python experiments/fused_step_smem.py [--joints 12,29] [--hidden 64,128,256]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import re
import sys

import jax
import jax.numpy as jnp

sys.path.insert(0, "tests")
from test_fused_step import _robot, _states  # noqa: E402

from stride_jax.dynamics import fused_layout, mlp, models, stride  # noqa: E402


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--joints", default="12,29")
    p.add_argument("--hidden", default="32,64,128,256")
    p.add_argument("--depth", type=int, default=3)
    args = p.parse_args(argv)
    for nj in map(int, args.joints.split(",")):
        spec, act = _robot(nj)
        lay = fused_layout.Layout.of(spec.nv, act.dof)
        for h in map(int, args.hidden.split(",")):
            cfg = stride.StructuredConfig(net=mlp.MLPConfig(hidden=h, depth=args.depth),
                                          shared_lnn=True, kernel="pallas-step")
            m = models.make("stride", spec, act, cfg)
            params = m.init(jax.random.key(0))
            q, qd, ctrl, keys = _states(spec, 64)
            row = dict(joints=nj, nv=spec.nv, entries=lay.entries, hidden=h)
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
    main()
