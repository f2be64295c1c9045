"""Closed-loop tracking against the sensors' noise (``stride closed-loop --sensor-noise F``): per
scenario and model, the velocity RMSE at each noise factor (the mean over trained seeds of each
seed's mean over its draws that stayed up), the falls, and how much the disturbance observer's
estimate moves from period to period (its step-to-step spread: what the noise puts into the
estimate the planner adds to every rollout step).

    python experiments/sensor_noise.py [LABEL=]RUN/closed_loop.json ... --out FILE  # FILE.md, .png

A ``LABEL=`` before a run marks its models as a variant (``stride (LABEL)``): runs of one
model with other planner settings (``--planning.velocity-filter``) stay apart from the rest.
Rows without ``sensor_noise`` ran on the exact state (factor 0); a noisy run's scenario is named
``SCENARIO_noiseF`` and is listed under ``SCENARIO``. The observer's spread is the row's
``observer_step_rms``, or read from its trace beside its ``closed_loop.json``
(``trace_<scenario>_<model>[_seed<s>].npz``; traces are not committed) for rows without it."""

from __future__ import annotations

import argparse
import json
import pathlib
import re
import shlex
import sys

import numpy as np

from stride_jax.control.episode import observer_step_rms
from stride_jax.io import atomic_write, atomic_write_text
from stride_jax.jobs.closed_loop import trace_name
from stride_paper.seeds import seed_means


def base_scenario(name: str) -> str:
    return re.sub(r"_noise[0-9.e+-]+$", "", name)


def observer_spread(folder: pathlib.Path, row: dict) -> float | None:
    """RMS over upright periods of the change of the observer's linear estimate from one period
    to the next (m/s^2): the row's ``observer_step_rms`` (runs since session 81's), else read
    from its trace; None where neither is there or there is no observer."""
    if row.get("observer_step_rms") is not None:
        return float(row["observer_step_rms"])
    path = folder / trace_name(row["scenario"], row["model"], row.get("episode", 0),
                               row.get("seed", 0))
    if not path.is_file():
        return None
    with np.load(path) as z:
        d, up = z["disturbance"], ~z["fallen"]
    return observer_step_rms(d, up) if np.any(d) else None


def collect(paths: list[str]) -> dict:
    """``{scenario: {model: {factor: dict(rmse, per_seed, falls, episodes, spread)}}}``."""
    groups: dict = {}
    for p in paths:
        label, _, where = p.rpartition("=")
        path = pathlib.Path(where)
        if not path.is_file():
            raise FileNotFoundError(f"{where}: no closed_loop.json")
        for r in json.loads(path.read_text())["rows"]:
            model = f"{r['model']} ({label})" if label else r["model"]
            key = (base_scenario(r["scenario"]), model, float(r.get("sensor_noise") or 0))
            groups.setdefault(key, []).append((path.parent, r))
    out: dict = {}
    for (sc, model, factor), got in groups.items():
        rows = [r for _, r in got]
        per_seed = list(seed_means(rows).values())
        spreads = [s for s in (observer_spread(f, r) for f, r in got) if s is not None]
        out.setdefault(sc, {}).setdefault(model, {})[factor] = dict(
            rmse=float(np.mean(per_seed)) if per_seed else float("nan"), per_seed=per_seed,
            falls=sum(bool(r["fell"]) for r in rows), episodes=len(rows),
            spread=float(np.mean(spreads)) if spreads else None)
    return out


def table(data: dict) -> list[str]:
    lines = []
    for sc, models in data.items():
        factors = sorted({f for m in models.values() for f in m})
        lines += [f"## {sc}", "",
                  "| model | " + " | ".join(f"noise x{f:g}: vel RMSE (falls/episodes)"
                                            for f in factors)
                  + " | " + " | ".join(f"observer step spread x{f:g} (m/s^2)" for f in factors)
                  + " |", "|---|" + "---:|" * (2 * len(factors))]
        for model, by in models.items():
            cells = [f"{by[f]['rmse']:.4f} ({by[f]['falls']}/{by[f]['episodes']})" if f in by
                     else "-" for f in factors]
            spread = [f"{by[f]['spread']:.2f}" if f in by and by[f]["spread"] is not None
                      else "-" for f in factors]
            lines.append(f"| {model} | " + " | ".join(cells + spread) + " |")
        lines.append("")
    return lines


def plot(data: dict, path: pathlib.Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, len(data), figsize=(7.5 * len(data), 4.0), squeeze=False)
    for ax, (sc, models) in zip(axes[0], data.items()):
        for model, by in models.items():
            fs = sorted(by)
            if len(fs) > 1:  # a curve; a variant run at one factor is the table's alone
                ax.plot(fs, [by[f]["rmse"] for f in fs], "o-", label=model)
        ax.set(title=f"{sc} (variants run at one noise factor: the table)",
               xlabel="sensor noise factor (x a well-instrumented robot's)",
               ylabel="velocity RMSE (m/s)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="upper left")
    fig.tight_layout()
    atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=120))
    plt.close(fig)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", nargs="+", help="closed_loop.json files, each LABEL=PATH or PATH")
    ap.add_argument("--out", required=True, help="output stem: STEM.md and STEM.png")
    a = ap.parse_args(argv)
    data = collect(a.runs)
    out = pathlib.Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    command = "python experiments/sensor_noise.py " + " ".join(
        shlex.quote(x) for x in (sys.argv[1:] if argv is None else argv))
    atomic_write_text(out.with_suffix(".md"), "\n".join(
        ["# Closed-loop tracking through noisier sensors", "", f"Command: `{command}`", "",
         "Velocity RMSE: the mean over trained seeds of each seed's mean over its draws that "
         "stayed up. Observer step spread: RMS of the change of the disturbance observer's "
         "linear estimate from one period to the next, over upright periods (what the sensors' "
         "noise puts into what the planner adds to every rollout step).", ""] + table(data)))
    plot(data, out.with_suffix(".png"))
    print("\n".join(table(data)))
    return data


if __name__ == "__main__":
    main()
