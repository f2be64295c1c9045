"""One diagnosis of logs from the nominal simulator with a joint-group effect planted, on any
registered robot or MJCF, printing what the calibration's refinement held (its screen takes the
joint groups of its best joint effects: ``CalibrateConfig.refine_finer``), the verdict and the
stage times: a check that the refinement and the finer effects work beyond the Go1.

    python experiments/probes/group_effect_check.py --robot g1 --effect damping@knee=1.0 \
        [--trajectories 8 --steps 200 --preset fast --seed 5]
"""

from __future__ import annotations

import argparse
import dataclasses
import time

from stride_jax.gap import diagnose, real
from stride_jax.sim import model


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robot", default="g1")
    ap.add_argument("--effect", default="damping@knee=1.0", help="NAME=VALUE, a scalar effect")
    ap.add_argument("--trajectories", type=int, default=8)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--seed", type=int, default=5)
    a = ap.parse_args()
    name, _, value = a.effect.partition("=")
    sm = model.load(a.robot)
    _, logged = real.generate(sm, {name: float(value)}, a.trajectories, a.steps, seed=a.seed)
    cfg = dataclasses.replace(diagnose.PRESETS[a.preset], progress=False)
    t0 = time.time()
    out = diagnose.diagnose(sm, logged, cfg, log=lambda s: print(f"[{time.time() - t0:6.1f} s] {s[:200]}", flush=True))
    r = out["calibration"].get("refined") or {}
    v = out["verdict"]
    print(f"refinement held {r.get('held_fixed')} ({(r.get('screen') or {}).get('replays')} screen replays)")
    print(f"verdict: {v['verdict']} {v['effects']} confident={v['confident']}; best "
          f"{out['which']['ranking'][0]['params'] if out.get('which') else None}")
    print(f"reason: {v['reason']}")
    print(f"stages (s): { {k: round(x, 1) for k, x in out['stage_seconds'].items()} }; total {time.time() - t0:.1f} s")


if __name__ == "__main__":
    main()
