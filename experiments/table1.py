"""The paper's Table I on one robot: data, every model x seeds, evaluation -> results/<robot>/.

    python experiments/table1.py --robot go1                       # full size (use a GPU)
    python experiments/table1.py --robot go1 --preset tiny          # minutes on a CPU
    python experiments/table1.py --robot go1 --minutes 7            # stop cleanly, resume later

Runs train side by side (``--parallel`` processes share the device: the models are small, so one
process leaves a GPU idle between kernel launches). Every run is resumable: run the same command
again and finished runs are skipped, stopped ones resume from their last checkpoint, and
evaluations are reused. Each run's log is ``<runs>/<model>-s<seed>/train.log``.
"""

from __future__ import annotations

import argparse
import os
import pathlib
import shlex
import subprocess
import sys
import time

PRESETS = {
    # data episodes, training preset and steps, eval preset
    "tiny": dict(episodes=8, train="tiny", steps=100, eval="tiny"),
    "paper": dict(episodes=1024, train="paper", steps=20_000, eval="default"),
}
MODELS = ("stride", "delan", "lnn_diffusion", "onn", "diffusion")


def _stride(*args: str) -> list[str]:
    return [sys.executable, "-m", "stride_jax.cli", *args]


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--robot", default="go1")
    p.add_argument("--preset", default="paper", choices=list(PRESETS))
    p.add_argument("--seeds", default="0,1,2")
    p.add_argument("--models", default=",".join(MODELS))
    p.add_argument("--steps", type=int, default=0, help="training steps (0: the preset's)")
    p.add_argument("--parallel", type=int, default=5, help="training processes at once")
    p.add_argument("--minutes", type=float, default=0.0,
                   help="wall-clock budget for training (0: none); runs stop cleanly at it")
    p.add_argument("--root", default="", help="data and runs folder (default: data/, runs/)")
    p.add_argument("--out", default="", help="results folder (default: results/<robot>)")
    args = p.parse_args(argv)
    preset = PRESETS[args.preset]
    steps = args.steps or preset["steps"]
    root = pathlib.Path(args.root or ".")
    data = root / "data" / f"{args.robot}-{args.preset}"
    runs = root / "runs" / f"{args.robot}-{args.preset}"
    command = "python experiments/table1.py " + shlex.join(sys.argv[1:] if argv is None else argv)
    t0 = time.time()
    deadline = t0 + 60 * args.minutes if args.minutes else 0.0

    if not (data / "meta.json").exists():
        subprocess.run(_stride("data", "--robot", args.robot, "--preset", "paper",
                               "--episodes", str(preset["episodes"]), "--out", str(data)),
                       check=True)
    print(f"[{time.time() - t0:.0f} s] data ready: {data}", flush=True)

    jobs = [(m, int(s)) for s in args.seeds.split(",") for m in args.models.split(",")]
    env = dict(os.environ, XLA_PYTHON_CLIENT_PREALLOCATE="false")
    train = {f"{m}-s{s}": _stride("train", "--robot", args.robot, "--model", m, "--preset",
                                  preset["train"], "--steps", str(steps), "--seed", str(s),
                                  "--data", str(data), "--out", str(runs / f"{m}-s{s}"),
                                  "--deadline", str(deadline)) for m, s in jobs}
    failed = _pool(train, runs, "train.log", args.parallel, env, t0)
    ok = [str(runs / name) for name in train if name not in failed]
    # Evaluate runs side by side (each caches its eval.json), then tabulate from those.
    evals = {name: _stride("eval", "--preset", preset["eval"], "--runs", str(runs / name),
                           "--out", str(runs / name / "eval_out"))
             for name in train if name not in failed}
    failed += _pool(evals, runs, "eval.log", args.parallel, env, t0)
    out = args.out or f"results/{args.robot}"
    subprocess.run(_stride("eval", "--preset", preset["eval"], "--runs", ",".join(ok),
                           "--out", out, "--label", command), check=True, env=env)
    print(f"[{time.time() - t0:.0f} s] wrote {out}/table.md", flush=True)
    if failed:
        raise SystemExit(f"failed: {failed} (see their logs under {runs})")


def _pool(cmds: dict[str, list[str]], runs: pathlib.Path, log_name: str, parallel: int,
          env: dict, t0: float) -> list[str]:
    """Runs the commands, ``parallel`` at a time, each logging to ``runs/<name>/<log_name>``;
    returns the names that failed."""
    pending, running, failed = list(cmds), [], []
    while pending or running:
        while pending and len(running) < parallel:
            name = pending.pop(0)
            (runs / name).mkdir(parents=True, exist_ok=True)
            log = open(runs / name / log_name, "a")
            running.append((name, subprocess.Popen(cmds[name], stdout=log, stderr=log, env=env),
                            log))
        time.sleep(1)
        for job in list(running):
            name, proc, log = job
            if proc.poll() is None:
                continue
            running.remove(job)
            log.close()
            if proc.returncode:
                failed.append(name)
            status = "ok" if proc.returncode == 0 else f"FAILED ({proc.returncode})"
            print(f"[{time.time() - t0:.0f} s] {log_name.split('.')[0]} {name}: {status}",
                  flush=True)
    return failed


if __name__ == "__main__":
    main()
