"""Where a Go1 diagnosis's calibration spends its time (issue 18, item 5): runs the calibration's
two passes (``calibrate.calibrate`` then ``calibrate.refine``, as ``diagnose`` does) on logs
written by ``experiments/gap_speed.py``, and tallies every replay by pass, time step and kind
(one settings value at a time, or a batch of N plans), with its seconds.

    python experiments/gap_speed.py --out /tmp/gap_speed --nominal shipped     # writes the logs
    python experiments/probes/calibration_time.py /tmp/gap_speed
"""

from __future__ import annotations

import collections
import json
import sys
import time

import stride_jax


def main() -> None:
    stride_jax.set_xla_flags()
    from stride_jax.gap import calibrate, diagnose, filters, fit, logs, nominal, sim

    sm = sim.for_replay(nominal.load("go1", "shipped"))
    _, trajs = logs.read(sys.argv[1], sm)
    cfg = diagnose.PRESETS["default"]
    trajs = [filters.preprocess(t, sm.robot.ctrl_dt, cfg.preprocess)[0] for t in trajs]
    tr_idx, te_idx = diagnose.split(len(trajs), cfg.holdout, cfg.seed)
    scale = diagnose.scale_of(sm, fit.subset(fit.make_data(trajs), tr_idx))
    train_k, test_k = (fit.make_data([trajs[i] for i in ix], cfg.steps) for ix in (tr_idx, te_idx))
    calls = []  # (seconds, replayed windows, time step, kind)
    one, many = calibrate.residual, calibrate.replay.residuals

    def timed_one(model, data, scale_, applied=None):
        t0 = time.time()
        r = one(model, data, scale_, applied)
        calls.append((time.time() - t0, len(data.start), model.mj.opt.timestep, "one" + ("+effect" if applied else "")))
        return r

    def timed_many(base, plans, data, scale_, rows=None):
        t0 = time.time()
        r = many(base, plans, data, scale_, rows)
        calls.append((time.time() - t0, len(data.start) * len(plans), base.mj.opt.timestep, f"batch of {len(plans)}"))
        return r

    calibrate.residual, calibrate.replay.residuals = timed_one, timed_many
    t0 = time.time()
    cal = calibrate.calibrate(sm, train_k, test_k, scale, cfg.calibrate, print)
    n_first = len(calls)
    print(f"first pass {time.time() - t0:.1f} s; discrete moves {json.dumps(cal.record['discrete_path'])}")
    calibrate.refine(sm, cal, train_k, test_k, scale, cfg.calibrate, cfg.fit.grid, print)
    print(f"both passes {time.time() - t0:.1f} s")
    for part, got in (("first pass", calls[:n_first]), ("refine (screen and second pass)", calls[n_first:])):
        tally = collections.defaultdict(lambda: [0, 0.0])
        for sec, n, dt, kind in got:
            tally[(dt * 1e3, kind, n)][0] += 1
            tally[(dt * 1e3, kind, n)][1] += sec
        print(f"{part}: time step (ms), kind, windows replayed per call -> calls, seconds")
        for (dt, kind, n), (c, sec) in sorted(tally.items(), key=lambda kv: -kv[1][1]):
            print(f"  {dt:4.1f} ms  {kind:14s} {n:6d}  {c:3d} calls  {sec:6.1f} s")


if __name__ == "__main__":
    main()
