"""A blind benchmark whose "real" logs come from independent code and independent simulator settings.

The first benchmark (:mod:`stride_jax.jobs.gap_bench`) makes its "real" logs with the diagnosis's own
effect code on the nominal model: the only difference is the planted effect, a self-consistent
check. Here the "real" robot is written apart from the tool (:mod:`stride_jax.jobs.gap_bench_real`,
which imports none of the diagnosis's effect code): the robot's MJCF as shipped with simulator
settings drawn per case (time step, integrator, cone, contact parameters, collision set), its own
planting of the effects, its own gait controller stepped with ``mujoco.mj_step`` and its own Go1
sensor model. Logs go through the documented log format on disk (``logs.write`` / ``logs.read``)
and are diagnosed with the shipped nominal model (:func:`stride_jax.gap.nominal.load`).

This module holds the presets, the cases and the resumable run; the scores (``top1_single``,
``top1_pairs``, ``median_shrink_single``, ``confident_false``, ``control_verdict`` and the
figures beside them) are :mod:`stride_jax.jobs.gap_bench_score`'s.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import pathlib
import tempfile
import time
from typing import Any

from stride_jax import io
from stride_jax.gap import diagnose, logs, nominal
from stride_jax.jobs import gap_bench as bench
from stride_jax.jobs import gap_bench_real as real
from stride_jax.jobs import gap_bench_score as scoring

@dataclasses.dataclass(frozen=True)
class IndependentConfig:
    """A preset of the independent benchmark.

    Attributes:
      robot: ``go1`` or ``pendulum`` (the controllers here know these two).
      trajectories, steps: per case (control steps per trajectory).
      singles: planted single in-library effects, ``((name, value), ...)``; ``delay`` in seconds.
      pairs: planted pairs, ``(((name, value), (name, value)), ...)``.
      out_of_library: planted effects the library lacks.
      noise: the noise settings to run (False: clean, True:
        :class:`stride_jax.jobs.gap_bench_real.Go1Sensors`).
      diagnose: preset of the diagnosis (``stride_jax.gap.diagnose.PRESETS``).
      pairs_of: override of the diagnosis's ``pairs_of`` (-1: the preset's).
      seed: of the cases (settings, controller, noise).
      name: of the result files.
      sensor_spec: the noisy logs carry the sensors' noise levels in their header
        (``velocity_noise``, as a real robot's logs can from its sensors' specification), and the
        diagnosis computes its noise floor from them instead of reading it off the residuals.
      controls: no-effect cases, each with its own drawn simulator settings (cases ``0 ..
        controls - 1``; with one, the other cases keep their draws): how often the tool calls a
        physical effect where only the simulator's form differs.
    """

    robot: str
    trajectories: int
    steps: int
    singles: tuple
    pairs: tuple = ()
    out_of_library: tuple = ()
    noise: tuple = (False, True)
    diagnose: str = "fast"
    pairs_of: int = -1
    seed: int = 1
    name: str = "gap_bench_go1_independent"
    sensor_spec: bool = False
    controls: int = 1

    def __post_init__(self):
        if self.controls < 1:
            raise ValueError(f"controls must be at least 1 (the benchmark's control case), got {self.controls}")


PRESETS = {
    # CI: the pendulum, a control and one effect, clean logs, the tiny diagnosis without pairs
    "tiny": IndependentConfig(robot="pendulum", trajectories=4, steps=80, singles=(("damping", 0.3),),
                              noise=(False,), diagnose="tiny", pairs_of=0, name="gap_bench_pendulum_independent"),
    # the Go1: every in-library effect that is not a simulator setting, damping on the calf joints
    # only (a finer effect), four pairs (the first two each with an effect the other can stand in
    # for, the last two with effects on different channels), two effects out of library, the
    # control; clean and noisy; 6 x 200 steps (4 s) per case
    "default": IndependentConfig(
        robot="go1", trajectories=6, steps=200,
        singles=(("damping", 1.5), ("frictionloss", 0.8), ("armature", 0.04), ("delay", 0.01),
                 ("torque_scale", 0.65), ("torque_limit", 0.4), ("kp_scale", 0.7), ("ground_friction", 0.3),
                 ("payload", 2.5), ("com_offset", (0.03, 0.0, 0.0)), ("deadzone", 0.04), ("damping@calf", 2.0)),
        pairs=((("damping", 1.0), ("delay", 0.006)), (("payload", 2.0), ("torque_scale", 0.8)),
               (("armature", 0.04), ("delay", 0.01)), (("damping", 1.5), ("torque_limit", 0.5))),
        out_of_library=(("joint_stiffness", 10.0), ("quadratic_drag", 0.05))),
}
# effects on some joints only, one of each joint and actuator kind, over the joint groups the
# diagnosis knows (joint type, leg); the planted part is matched in the joints' names by the
# independent generator, the same joints as the diagnosis's group of that name on the Go1
PRESETS["groups"] = dataclasses.replace(
    PRESETS["default"], singles=(("frictionloss@hip", 0.6), ("armature@thigh", 0.05), ("kp_scale@FL", 0.6),
                                 ("torque_limit@calf", 0.5), ("damping@RR", 1.0)),
    pairs=(), out_of_library=(), name="gap_bench_go1_independent_groups")
# the same cases on shorter logs: what a 2-core CPU can run in a few hours
PRESETS["small"] = dataclasses.replace(PRESETS["default"], trajectories=5, steps=100,
                                       name="gap_bench_go1_independent_small")
# the noisy cases again with the sensors' noise levels in the logs' header (session 44: the floor
# read off the residuals is off by 0.08-3.1 x, results/gap_noise_floor_check.md)
PRESETS["sensor_spec"] = dataclasses.replace(PRESETS["default"], noise=(True,), sensor_spec=True,
                                             name="gap_bench_go1_independent_sensor_spec")
# the detection's level on the Go1 (issue 18, item 3): 20 no-effect cases, each with its own drawn
# simulator settings, clean and noisy; a call of a physical effect on any of them is a false one
PRESETS["controls"] = dataclasses.replace(PRESETS["default"], singles=(), pairs=(), out_of_library=(), controls=20,
                                          name="gap_bench_go1_independent_controls")


def cases(cfg: IndependentConfig) -> list[dict[str, Any]]:
    """Every case: ``{"kind", "planted"}`` (control, single, pair, out_of_library)."""
    out = [{"kind": "control", "planted": {}} for _ in range(cfg.controls)]
    out += [{"kind": "single", "planted": {n: v}} for n, v in cfg.singles]
    out += [{"kind": "pair", "planted": dict(p)} for p in cfg.pairs]
    out += [{"kind": "out_of_library", "planted": {n: v}} for n, v in cfg.out_of_library]
    return out


def real_logs(cfg: IndependentConfig, index: int, noisy: bool):
    """Case ``index``'s ``(clean, logged)`` trajectories, drawn settings and "real" model without the
    planted effects (:func:`stride_jax.jobs.gap_bench_real.generate`)."""
    return real.generate(cfg.robot, cases(cfg)[index]["planted"], cfg.seed, index, cfg.trajectories, cfg.steps, noisy)


# ----------------------------------------------------------------------------- running


def diagnose_row(cfg: IndependentConfig, index: int, noisy: bool) -> dict[str, Any]:
    """Generates case ``index`` independently, writes and reads it as a log folder, diagnoses it
    with the shipped nominal model and scores it (a pure function of its arguments)."""
    return diagnose_case(cfg, index, noisy)[0]


def as_read(cfg: IndependentConfig, index: int, noisy: bool):
    """Case ``index``'s logs as a user would hand them over: written to the documented log folder and
    read back against the shipped nominal model. ``(nominal model, logged trajectories, clean
    trajectories, drawn settings, "real" model)``."""
    sm = nominal.load(cfg.robot, "shipped")
    clean, logged, settings, form = real_logs(cfg, index, noisy)
    with tempfile.TemporaryDirectory() as tmp:
        logs.write(tmp, sm, logged, notes=f"independent benchmark case {index}",
                   velocity_noise=real.Go1Sensors().velocity_noise(sm) if noisy and cfg.sensor_spec else None)
        h, trajs = logs.read(tmp, sm)
    return sm, trajs, clean, settings, form, logs.velocity_std(h, sm)


def diagnose_case(cfg: IndependentConfig, index: int, noisy: bool
                  ) -> tuple[dict[str, Any], dict[str, Any]]:
    """:func:`diagnose_row`'s scored row and the whole diagnosis it scored
    (``experiments/gap_one_row.py`` keeps both, to read a verdict without the benchmark)."""
    t0 = time.time()
    sm, trajs, clean, settings, form, velocity_std = as_read(cfg, index, noisy)
    dcfg = diagnose.PRESETS[cfg.diagnose]
    if cfg.pairs_of >= 0:
        dcfg = dataclasses.replace(dcfg, pairs_of=cfg.pairs_of)
    res = diagnose.diagnose(sm, trajs, dcfg, log=lambda s: None, velocity_std=velocity_std)
    held = [t for t in clean if t.name in set(res["heldout"])]
    row = scoring.score(sm, cases(cfg)[index], res, held, settings, form, dcfg.attribute_min, dcfg.pair_material,
                        dcfg.fit)
    fc = (res.get("which") or {}).get("form_check")
    # the form check runs only on a call that was confident before it: with it, the row says what
    # the call would have been without the check
    form_check = {k: fc[k] for k in ("effect", "split", "slow", "fast", "differs")} if fc else None
    return row | {"noisy": noisy, "case": index, "form_check": form_check,
                  "row_seconds": time.time() - t0}, res


def run(cfg: IndependentConfig, out_dir: str | os.PathLike = "results", command: str = "", log=print,
        workers: int = 1, threads: int = 1, minutes: float | None = None) -> dict[str, Any]:
    """Runs the benchmark resumably (rows in ``<out>/<name>_cases/``, as :func:`stride_jax.jobs.gap_bench.run`)
    and writes ``<out>/<name>.{md,json}`` once every row is done."""
    if workers < 1 or threads < 1:
        raise bench.BenchError(f"workers and threads must be at least 1, got {workers} and {threads}")
    folder = bench.rows_dir(cfg, out_dir)
    code, t0 = io.code_version(), time.time()
    done = bench.load_rows(folder, cfg) if folder.is_dir() else {}
    todo = [(i, nz) for i in range(len(cases(cfg))) for nz in cfg.noise if (i, nz) not in done]
    total = len(todo) + len(done)
    log(f"{cfg.name}: {len(done)} of {total} rows already in {folder}; {len(todo)} to run with {workers} worker(s)")

    def save(row):
        row = bench.save_row(folder, cfg, row, code)
        done[(row["case"], row["noisy"])] = {"row": row, "code": code}
        log(f"[{time.time() - t0:6.0f} s] {len(done)}/{total} {'noisy' if row['noisy'] else 'clean'} {row['kind']:14s} "
            f"{row['planted']} -> {row['verdict']} {row['named']} conf={row['confident']} calibration="
            f"{row['calibration']} ratio={row.get('shrink_ratio')} ({row['row_seconds']:.0f} s)")

    deadline = t0 + 60 * minutes if minutes is not None else math.inf
    bench._compute(cfg, todo, workers, threads, deadline, save,
                   pathlib.Path(tempfile.gettempdir()) / "stride_jax", row_fn=diagnose_row)
    if len(done) < total:
        log(f"stopped after {(time.time() - t0) / 60:.1f} min: {len(done)} of {total} rows done (in {folder}); "
            "rerun the same command to continue")
        return {"complete": False, "done": len(done), "total": total, "rows_dir": str(folder)}
    rows = [done[k]["row"] for k in sorted(done)]
    summ = scoring.summary(rows)
    seconds = float(sum(r.get("row_seconds", r["seconds"]) for r in rows))
    keys = ("top1_single", "top1_pairs", "median_shrink_single", "confident_false", "control_verdict")
    result = {k: {n: s.get(k) for n, s in summ.items()} for k in keys}
    result |= {"command": command, "config": dataclasses.asdict(cfg), "summary": summ, "cases": rows,
               "seconds": seconds, "code": sorted({d["code"] for d in done.values()})}
    out = pathlib.Path(out_dir)
    io.atomic_write_text(out / f"{cfg.name}.json", json.dumps(result, indent=1, default=float))
    io.atomic_write_text(out / f"{cfg.name}.md", scoring.markdown(cfg, rows, summ, command, seconds))
    log(json.dumps(summ, indent=1, default=float))
    return result | {"complete": True}
