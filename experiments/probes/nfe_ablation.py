"""Why STRIDE's rollout error grows with NFE away from the NFE it was trained at: the same flow
trained with its acceleration loss through the integrated central sample (``central``, the
default: Algorithm 1), through a random sample (``sample``), or not at all (``prior``: flow
matching alone trains the flow), each swept over NFE at test time.

    python experiments/probes/nfe_ablation.py --root /tmp/nfe_ablation --out results/table1/nfe_ablation_go1_cpu

CPU size (Table I's ``cpu`` preset: 128 x 3, batch 256, 4000 steps, 96 Go1 explorer episodes);
resumable (the data and finished runs are reused). Writes ``nfe_ablation.{json,md}``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib
import sys
import time

import stride_jax


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--root", default="/tmp/nfe_ablation")
    p.add_argument("--out", default="results/table1/nfe_ablation_go1_cpu")
    p.add_argument("--robot", default="go1")
    p.add_argument("--episodes", type=int, default=96)
    p.add_argument("--steps", type=int, default=4000)
    p.add_argument("--variants", default="central,sample,prior")
    p.add_argument("--nfe", default="1,2,4,8,16")
    p.add_argument("--seeds", default="0")
    p.add_argument("--windows", type=int, default=128)
    p.add_argument("--samples", type=int, default=4)
    args = p.parse_args(argv)
    from stride_jax.eval import horizon, nfe as nfe_lib
    from stride_jax.eval.runs import load_run
    from stride_jax.io import atomic_write_text
    from stride_jax.jobs import data as data_job, train as train_job

    root, out = pathlib.Path(args.root), pathlib.Path(args.out)
    data = root / "data" / f"{args.robot}-cpu"
    if not (data / "meta.json").is_file():
        data_job.generate(data_job.DataConfig(robot=args.robot, episodes=args.episodes,
                                              out=str(data)))
    preset = train_job.PRESETS["default"]
    nfes = [int(n) for n in args.nfe.split(",")]
    hcfg = horizon.HorizonConfig(windows=args.windows, samples=args.samples)
    result = {"command": "python experiments/probes/nfe_ablation.py " + " ".join(
        sys.argv[1:] if argv is None else argv), "variants": {}, "horizon": dataclasses.asdict(hcfg)}
    t0 = time.time()
    for variant in args.variants.split(","):
        runs = []
        for seed in [int(s) for s in args.seeds.split(",")]:
            cfg = dataclasses.replace(
                preset, robot=args.robot, model="stride", data=str(data), acc_through=variant,
                loop=dataclasses.replace(preset.loop, steps=args.steps, seed=seed),
                out=str(root / "runs" / f"stride-{variant}-s{seed}"))
            runs.append(load_run(train_job.run(cfg)))
        result["variants"][variant] = nfe_lib.sweep(runs, nfes, hcfg, root / "cache", 3, 64)
        print(f"[{time.time() - t0:.0f} s] {variant}: "
              f"{[round(e, 3) for e in result['variants'][variant]['error_mean']]}", flush=True)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "nfe_ablation.json", json.dumps(result, indent=1))
    lines = [f"# STRIDE's 30-step error against test-time NFE, by what its acceleration loss "
             f"trains ({args.robot}, CPU size)", "", f"Command: `{result['command']}`", "",
             f"Cumulative normalised {hcfg.horizon}-step error, {hcfg.windows} test windows, "
             f"{hcfg.samples} samples, mean ± std over seeds {args.seeds}; trained at the "
             "model's default NFE (2).", "",
             "| acc_through | " + " | ".join(f"NFE {n}" for n in nfes) + " |",
             "|---|" + "---:|" * len(nfes)]
    for variant, r in result["variants"].items():
        lines.append(f"| {variant} | " + " | ".join(
            f"{m:.3f} ± {s:.3f}" for m, s in zip(r["error_mean"], r["error_std"])) + " |")
    atomic_write_text(out / "nfe_ablation.md", "\n".join(lines) + "\n")
    print(f"wrote {out}/nfe_ablation.md")


if __name__ == "__main__":
    stride_jax.set_xla_flags()
    main()
