"""Times one Go1 diagnosis (issue 18, item 5): 12 trajectories x 8 s at 50 Hz, default preset.

    python experiments/gap_speed.py --out /tmp/gap_speed [--effects '{"damping@calf": 0.8}'] [--noise] [--repeat 2]

Writes the logs (12 full-length trajectories of the Go1 explorer on the nominal model with the planted
effect: episodes where the robot falls are skipped), runs ``stride_jax.gap.diagnose.diagnose`` under cProfile
``--repeat`` times, and prints the wall time of each run, its stages, the verdict with its reason and the profile's
top lines (of the fastest run). The machine's load is printed before and after each run: other jobs on a
small machine inflate the time.
"""

from __future__ import annotations

import argparse
import cProfile
import io
import json
import os
import pstats
import time

import stride_jax


def main() -> None:
    stride_jax.set_xla_flags()
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True)
    ap.add_argument("--effects", default='{"damping@calf": 0.8}')
    ap.add_argument("--trajectories", type=int, default=12)
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--preset", default="default")
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--noise", action="store_true", help="through a real Go1's sensors (real.SensorNoise)")
    ap.add_argument("--nominal", default="shipped", help="the nominal model: shipped (the MJCF as shipped, "
                    "what `stride gap diagnose` uses) or training (the MJX-training edit)")
    a = ap.parse_args()
    from stride_jax.gap import diagnose, logs, nominal, real

    sm = nominal.load("go1", a.nominal)
    _, lg = real.generate(sm, json.loads(a.effects), 4 * a.trajectories, a.steps, a.seed,
                          real.SensorNoise() if a.noise else None)
    full = [t for t in lg if len(t.t) == a.steps][:a.trajectories]
    if len(full) < a.trajectories:
        raise SystemExit(f"only {len(full)} of {4 * a.trajectories} episodes ran {a.steps} steps without a fall")
    logs.write(a.out, sm, full, notes=f"experiments/gap_speed.py, effects {a.effects}")
    _, trajs = logs.read(a.out, sm)
    cfg = diagnose.PRESETS[a.preset]
    runs = []
    for i in range(a.repeat):
        load0 = os.getloadavg()[0]
        prof = cProfile.Profile()
        t0 = time.time()
        prof.enable()
        out = diagnose.diagnose(sm, trajs, cfg, log=lambda s: print(f"[{time.time() - t0:6.1f} s] {s[:160]}", flush=True))
        prof.disable()
        sec = time.time() - t0
        s = io.StringIO()
        pstats.Stats(prof, stream=s).sort_stats("cumulative").print_stats(25)
        runs.append({"seconds": sec, "load_before": load0, "load_after": os.getloadavg()[0],
                     "stages": {k: round(v, 1) for k, v in out["stage_seconds"].items()},
                     "which_stages": (out.get("which") or {}).get("seconds"),
                     "verdict": out["verdict"]["verdict"], "effects": out["verdict"]["effects"],
                     "confident": out["verdict"]["confident"], "reason": out["verdict"].get("reason"),
                     "indistinguishable": (out["verdict"].get("indistinguishable_set") or {}).get("effects"),
                     "shortlist": (out["screen"] or {}).get("shortlist"), "profile": s.getvalue()})
        print(json.dumps({k: v for k, v in runs[-1].items() if k != "profile"}), flush=True)
    best = min(runs, key=lambda r: r["seconds"])
    print(f"fastest of {len(runs)}: {best['seconds']:.1f} s; all: {[round(r['seconds'], 1) for r in runs]}")
    print(best["profile"])


if __name__ == "__main__":
    main()
