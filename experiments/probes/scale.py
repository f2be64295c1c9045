"""Data generation and training throughput on 1, 2, ... devices of one host, in one run
-> results/scale/scale.{md,json}.

    python experiments/probes/scale.py --robot go1 --devices 1,2 --out results/scale            # GPUs
    python experiments/probes/scale.py --robot go1 --devices 1,2 --platform cpu --out /tmp/s    # forced host devices

Each device count runs in its own process (JAX fixes its devices when it starts): on GPUs it
sees the first ``d`` of them (``CUDA_VISIBLE_DEVICES``), on a CPU ``d`` forced host devices
(``--xla_force_host_platform_device_count``). In it:

- **data**: the MJX collection of ``stride data`` (``rollout_mjx.collect``: worlds split over
  the devices), timed on its second call (the first compiles); simulator steps per second, with
  the records copied to the host (``data``) and on the devices alone (``device``: the jitted
  collection function, blocked on, nothing copied). ``--impl warp`` runs MuJoCo Warp's physics.
  ``--data-batches`` > 1 splits the worlds into that many calls, as ``stride data --batch`` does
  (each batch's copy overlaps the next one's simulation). ``--split`` (as ``stride data
  --split``): ``threads`` gives each device its own program, calls and copies from its own host
  thread; ``shard`` splits each call over the devices with XLA's partitioner.
- **training**: ``stride train`` on one shared dataset (the minibatch split over the devices,
  XLA all-reducing the gradients), steps per second read from ``metrics.csv`` between its first
  and last validation (compilation excluded). ``--per-device-batch`` keeps each device's share
  fixed, of the minibatch and of the data probe's worlds (weak scaling); otherwise the global
  batch and worlds are fixed (strong scaling).

``--processes`` (data only): a device count ``d`` runs ``d`` processes side by side, each seeing
one device and collecting its own share of the worlds (``--worlds`` each) with its own copy to
the host, as several ``stride_jax.distributed`` processes of one host do before process 0
gathers their shares (the gather and the write are not timed). The processes start each timed
call together (a file barrier); a row's rate is all their steps over the span from the first
start to the last end.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import subprocess
import sys
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parents[2]


def child(args) -> None:
    import stride_jax

    stride_jax.set_xla_flags()
    import csv

    import jax

    from stride_jax import cli
    from stride_jax.sim import model, rollout_mjx

    n = len(jax.local_devices())
    assert n == args.d, f"asked for {args.d} devices, JAX sees {n}"
    procs = args.procs or 1
    barrier_no = iter(range(1 << 30))

    def barrier():  # every process of a --processes row waits for the others here
        if procs == 1:
            return
        k = next(barrier_no)
        d = pathlib.Path(args.barrier)
        (d / f"{k}.{args.rank}").touch()
        while len(list(d.glob(f"{k}.*"))) < procs:
            time.sleep(0.005)

    spans, dev_spans = [], []
    sm = model.load(args.robot)
    n_steps = max(1, int(round(args.seconds / sm.robot.ctrl_dt)))
    worlds = args.worlds * (n if args.per_device_batch else 1)  # weak scaling: a share per device
    batch = worlds // args.data_batches
    times = []
    for _ in range(2):  # the first call compiles
        barrier()
        t, t_wall = time.perf_counter(), time.time()
        ep = rollout_mjx.collect(sm, jax.random.key(args.rank), worlds, n_steps, batch,
                                 impl=args.impl, split=args.split)
        jax.block_until_ready(ep.records.q)
        times.append(time.perf_counter() - t)
        spans.append((t_wall, time.time()))
    call = rollout_mjx.device_call(sm, n_steps, batch, impl=args.impl, split=args.split,
                                   key=jax.random.key(0))
    dev = []
    for _ in range(3):
        barrier()
        t, t_wall = time.perf_counter(), time.time()
        call()
        dev.append(time.perf_counter() - t)
        dev_spans.append((t_wall, time.time()))
    sim_steps = worlds * n_steps * sm.n_substeps
    row = dict(devices=n, platform=jax.default_backend(), device_kind=jax.devices()[0].device_kind,
               robot=args.robot, impl=args.impl, split=args.split, worlds=worlds,
               data_batch=batch,
               control_steps=n_steps, data_seconds=times[1],
               data_sim_steps_per_s=sim_steps / times[1],
               device_sim_steps_per_s=batch * n_steps * sm.n_substeps / min(dev[1:]),
               data_span=spans[1], device_spans=dev_spans[1:],
               device_sim_steps=batch * n_steps * sm.n_substeps)
    if args.no_train:
        pathlib.Path(args.result).write_text(json.dumps(row))
        print(json.dumps(row), flush=True)
        return
    batch = args.batch * (n if args.per_device_batch else 1)
    with tempfile.TemporaryDirectory() as tmp:
        cli.main(["train", "--robot", args.robot, "--model", args.model, "--preset", "paper",
                  "--data", args.data, "--steps", str(args.train_steps), "--batch", str(batch),
                  "--eval-every", str(args.train_steps // 4),
                  "--ckpt-every", str(args.train_steps), "--out", f"{tmp}/run"])
        rows = list(csv.DictReader(open(f"{tmp}/run/metrics.csv")))
    first, last = rows[0], rows[-1]
    steps = int(last["step"]) - int(first["step"])
    row.update(model=args.model, batch=batch, train_steps_timed=steps,
               train_steps_per_s=steps / (float(last["time"]) - float(first["time"])))
    row["train_examples_per_s"] = row["train_steps_per_s"] * batch
    pathlib.Path(args.result).write_text(json.dumps(row))
    print(json.dumps(row), flush=True)


def merge_processes(parts: list[dict]) -> dict:
    """One row from the rows of processes that ran side by side: all their simulator steps over
    the span from the first start to the last end (data: the timed call; on device: the best of
    the repetitions, each started together)."""
    row = dict(parts[0], devices=len(parts), processes=len(parts),
               worlds=sum(p["worlds"] for p in parts))
    steps = sum(p["data_sim_steps_per_s"] * p["data_seconds"] for p in parts)
    span = max(p["data_span"][1] for p in parts) - min(p["data_span"][0] for p in parts)
    row.update(data_seconds=span, data_sim_steps_per_s=steps / span)
    dev_steps = sum(p["device_sim_steps"] for p in parts)
    reps = zip(*(p["device_spans"] for p in parts))
    row["device_sim_steps_per_s"] = max(
        dev_steps / (max(e for _, e in rep) - min(s for s, _ in rep)) for rep in reps)
    row["per_process_data_sim_steps_per_s"] = [p["data_sim_steps_per_s"] for p in parts]
    return row


def _env(platform: str, d: int, first: int = 0) -> dict:
    env = dict(os.environ, PYTHONPATH=f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}")
    if platform == "cpu":  # set_xla_flags makes the devices and keeps its CPU-safe flags; a pool
        env["JAX_PLATFORMS"] = "cpu"  # that lets MJX run on all of them (rollout_mjx.mjx_devices)
        env["STRIDE_HOST_DEVICES"] = str(d)
        if d > 1:
            from stride_jax import _env as stride_env
            env.setdefault("NPROC", str(stride_env.pool_needed(d)))
    else:
        env["CUDA_VISIBLE_DEVICES"] = ",".join(str(i) for i in range(first, first + d))
    return env


_SPLITS = {"shard": "by XLA's partitioner, one program",
           "threads": "each device its own program, calls and copies from its own host thread"}


def write(rows: list[dict], out: pathlib.Path, command: str) -> None:
    from stride_jax.io import atomic_write_text

    base = rows[0]
    lines = [f"# Throughput against device count ({base['robot']}, {base['platform']}: "
             f"{base['device_kind']})", "",
             f"Command: `{command}`", "",
             "| devices | worlds | data sim steps/s | speed-up | on device | speed-up "
             "| batch | train steps/s | examples/s | speed-up |",
             "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    train, nan = "train_steps_per_s" in base, float("nan")  # rows from before the device column
    for r in rows:
        dev = r.get("device_sim_steps_per_s", nan)
        cells = [str(r["devices"]), str(r["worlds"]), f"{r['data_sim_steps_per_s']:,.0f}",
                 f"{r['data_sim_steps_per_s'] / base['data_sim_steps_per_s']:.2f}x",
                 f"{dev:,.0f}", f"{dev / base.get('device_sim_steps_per_s', nan):.2f}x"]
        if train:
            cells += [str(r["batch"]), f"{r['train_steps_per_s']:,.1f}",
                      f"{r['train_examples_per_s']:,.0f}",
                      f"{r['train_examples_per_s'] / base['train_examples_per_s']:.2f}x"]
        else:
            cells += ["-"] * 4
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", f"Data: the worlds of each row x {base['control_steps']} control steps, "
              f"{base.get('impl', 'jax')} physics, in calls of "
              f"{base.get('data_batch', base['worlds'])} worlds split over the devices "
              f"({_SPLITS[base.get('split', 'shard')]}); "
              f"'data' includes copying the records to the host, "
              f"'on device' is one call with nothing copied."]
    if base.get("processes"):
        lines += ["One process per device, side by side, each collecting and copying its own "
                  "share (`--processes`): a row's rate is all their steps over the span from "
                  "the first start to the last end."]
    if train:
        lines += [f"Training: `{base['model']}` at the paper preset's 256 x 3, the row's batch "
                  f"split over the devices, {base['train_steps_timed']} timed steps."]
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "scale.json", json.dumps(rows, indent=1))
    atomic_write_text(out / "scale.md", "\n".join(lines) + "\n")


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--robot", default="go1")
    p.add_argument("--model", default="stride")
    p.add_argument("--devices", default="1,2", help="device counts, e.g. 1,2")
    p.add_argument("--platform", default="gpu", choices=("gpu", "cpu"))
    p.add_argument("--worlds", type=int, default=4096)
    p.add_argument("--seconds", type=float, default=2.0, help="episode length of the data probe")
    p.add_argument("--data", default="", help="dataset for training (default: made first)")
    p.add_argument("--data-episodes", type=int, default=512)
    p.add_argument("--train-steps", type=int, default=2000)
    p.add_argument("--batch", type=int, default=1024)
    p.add_argument("--per-device-batch", action="store_true")
    p.add_argument("--impl", default="jax", choices=("jax", "warp"), help="the data's physics")
    p.add_argument("--data-batches", type=int, default=1, help="calls the worlds are split into")
    p.add_argument("--split", default="threads", choices=("threads", "shard"),
                   help="how one process's devices share the worlds (rollout_mjx.collect)")
    p.add_argument("--no-train", action="store_true", help="data only")
    p.add_argument("--processes", action="store_true",
                   help="data only: one process per device, side by side (module docstring)")
    p.add_argument("--out", default="results/scale")
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--d", type=int, default=1, help=argparse.SUPPRESS)
    p.add_argument("--result", default="", help=argparse.SUPPRESS)
    p.add_argument("--procs", type=int, default=0, help=argparse.SUPPRESS)
    p.add_argument("--rank", type=int, default=0, help=argparse.SUPPRESS)
    p.add_argument("--barrier", default="", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child:
        return child(args)
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    counts = [int(d) for d in args.devices.split(",")]
    if args.processes:
        args.no_train = True
    data = args.data
    if not data and not args.no_train:
        data = str(out / f"data_{args.robot}")
        if not (pathlib.Path(data) / "meta.json").exists():
            subprocess.run([sys.executable, "-m", "stride_jax.cli", "data", "--robot", args.robot,
                            "--backend", "mjx", "--episodes", str(args.data_episodes),
                            "--out", data], env=_env(args.platform, 1), check=True)
    rows = []
    for d in counts:
        result = out / f"devices_{d}.json"
        opts = ["--robot", args.robot, "--model", args.model, "--worlds", str(args.worlds),
                "--seconds", str(args.seconds), "--data", data,
                "--train-steps", str(args.train_steps), "--batch", str(args.batch),
                "--impl", args.impl, "--data-batches", str(args.data_batches),
                "--split", args.split]
        opts += ["--per-device-batch"] * args.per_device_batch + ["--no-train"] * args.no_train
        child_cmd = lambda devices, res: [sys.executable, __file__, "--child", "--d",
                                          str(devices), "--result", str(res), *opts]
        print(f"--- {d} device(s)" + " in as many processes" * args.processes, flush=True)
        if not args.processes:
            subprocess.run(child_cmd(d, result), env=_env(args.platform, d), check=True)
            rows.append(json.loads(result.read_text()))
        else:
            with tempfile.TemporaryDirectory() as barrier:
                res = [out / f"devices_{d}_rank_{i}.json" for i in range(d)]
                jobs = [subprocess.Popen(child_cmd(1, res[i]) + [
                    "--procs", str(d), "--rank", str(i), "--barrier", barrier],
                    env=_env(args.platform, 1, i)) for i in range(d)]
                if any(j.wait() for j in jobs):
                    raise SystemExit(f"a process of the {d}-device row failed")
            rows.append(merge_processes([json.loads(r.read_text()) for r in res]))
        write(rows, out, "python experiments/probes/scale.py " + " ".join(argv or sys.argv[1:]))
    print((out / "scale.md").read_text())


if __name__ == "__main__":
    main()
