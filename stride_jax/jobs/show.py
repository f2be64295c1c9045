"""``stride show``: what trained pendulum models predict near the upright, against the truth.

The last step of ``make demo``. For a STRIDE run and a DeLaN run trained beside it on the same
pendulum data, it writes the phase portrait of :mod:`stride_jax.eval.phase` (the vector field of
mean one-step accelerations, open-loop trajectories with sampled residuals, and the one-step
acceleration distributions at states near the upright, each against MuJoCo under the data's
hidden randomisation) and prints one line of accuracy: per model the field RMSE and the
near-upright distribution distance (1-Wasserstein, rad/s^2) as a multiple of the floor no
deterministic model can beat.
"""

from __future__ import annotations

import dataclasses
import json
import math
import pathlib

import numpy as np

from stride_jax.eval import horizon, phase, runs
from stride_jax.io import atomic_write_text, code_version


@dataclasses.dataclass(frozen=True)
class ShowConfig:
    """Attributes:
      stride: the STRIDE run folder (``stride train --model stride``).
      baseline: the run it is held against (DeLaN, ``stride train --model delan``).
      out: where ``phase_portrait.png`` and ``phase.json`` go.
      phase: the portrait's grid and draws (``eval.phase.PhaseConfig``).
    """

    stride: str = "runs/pendulum/stride"
    baseline: str = "runs/pendulum/delan"
    out: str = "runs/pendulum"
    phase: phase.PhaseConfig = phase.PhaseConfig()


PRESETS = {
    "tiny": ShowConfig(phase=phase.PhaseConfig(grid=7, worlds=8, samples=8, traj_steps=20,
                                               traj_samples=2)),
    # a laptop CPU in well under a minute
    "default": ShowConfig(phase=phase.PhaseConfig(grid=15, worlds=64, samples=64)),
    "paper": ShowConfig(),
}


def summary_line(numbers: dict, names: dict[str, str]) -> str:
    """One line: each model's field RMSE and near-upright W1 (and its multiple of the floor)."""
    floor = numbers["truth"]["w1_near_deterministic_floor"]
    parts = [f"{label}: field RMSE {numbers[n]['field_rmse']:.2f} rad/s², near-upright W1 "
             f"{numbers[n]['w1_near']:.2f} ({numbers[n]['w1_near_over_floor']:.2f} x the "
             f"deterministic floor {floor:.2f})" for n, label in names.items()]
    return "; ".join(parts)


def plot_phase(arrays: dict, numbers: dict, path: pathlib.Path, title: str = "") -> pathlib.Path:
    """Row 1: vector fields (streamlines of ``(qd, mean a)``) and trajectories, truth then each
    model; row 2: the one-step acceleration distribution at the probe states, and the
    near-upright distribution match per model."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [n for n in arrays["field"]]
    cols = max(len(names), len(arrays["probes"]) + 1)
    fig, ax = plt.subplots(2, cols, figsize=(4.2 * cols, 8.0), squeeze=False)
    Q, QD = arrays["Q"], arrays["QD"]
    colors = [f"C{i}" for i in range(len(arrays["starts"]))]
    for j, name in enumerate(names):
        a = ax[0, j]
        field = arrays["field"][name]
        speed = np.hypot(QD / np.abs(QD).max(), field / max(np.abs(field).max(), 1e-9))
        a.streamplot(Q[0], QD[:, 0], QD, field, color=speed, cmap="Greys", density=1.0,
                     linewidth=0.7, arrowsize=0.8)
        tq, tqd = arrays["traj"][name]  # [2 or S, K, T]
        for k, c in enumerate(colors):
            for s in range(tq.shape[0]):
                style = ("-" if s == 0 else "--") if name == "truth" else "-"
                a.plot(tq[s, k], tqd[s, k], style, color=c, lw=1.2 if name == "truth" else 0.8,
                       alpha=1.0 if name == "truth" or tq.shape[0] == 1 else 0.6)
            a.plot(*arrays["starts"][k], "o", color=c, ms=4)
        a.axvline(math.pi, color="k", lw=0.4, alpha=0.4)
        sub = ("MuJoCo, field: mean over hidden draws;\ntrajectories: bump + (solid) / - (dashed)"
               if name == "truth" else
               f"W1 near upright {numbers[name]['w1_near']:.2f} rad/s² "
               f"({numbers[name]['w1_near_over_floor']:.2f} x det. floor)")
        a.set(xlim=(Q.min(), Q.max()), ylim=(QD.min(), QD.max()), xlabel="q (rad)",
              ylabel="qd (rad/s)", title=f"{horizon.LABELS.get(name, name.title())}\n{sub}")
        a.title.set_fontsize(8)
    for j in range(len(names), cols):
        ax[0, j].axis("off")
    for i, (pq, pqd) in enumerate(arrays["probes"]):
        a = ax[1, i]
        t = arrays["probe_samples"]["truth"][:, i]
        lo, hi = np.percentile(t, [0.5, 99.5])
        pad = 0.3 * (hi - lo + 1e-3)
        bins = np.linspace(lo - pad, hi + pad, int(np.clip(len(t) // 4, 15, 50)))
        a.hist(t, bins=bins, density=True, color="k", alpha=0.35, label="truth")
        for name in names[1:]:
            smp = arrays["probe_samples"][name][:, i]
            color = horizon.COLORS.get(name)
            if smp.shape[0] > 1:
                a.hist(np.clip(smp, bins[0], bins[-1]), bins=bins, density=True,
                       histtype="step", lw=1.5, color=color, label=horizon.LABELS.get(name))
            else:
                a.axvline(smp[0], color=color, lw=1.5, label=horizon.LABELS.get(name))
        a.set(title=f"one-step acceleration at q = pi{pq - math.pi:+.2f}, qd = {pqd:+.2f}",
              xlabel="a (rad/s²)", ylabel="density")
        a.title.set_fontsize(8)
        a.legend(fontsize=7)
    a = ax[1, len(arrays["probes"])]
    models = names[1:]
    a.bar(range(len(models)), [numbers[n]["w1_near"] for n in models],
          color=[horizon.COLORS.get(n) for n in models])
    a.axhline(numbers["truth"]["w1_near_deterministic_floor"], color="k", ls="--",
              label="best deterministic model")
    a.set_xticks(range(len(models)), [horizon.LABELS.get(n, n) for n in models], fontsize=8)
    a.set(ylabel="W1 to truth near upright (rad/s²)", title="distribution match near upright")
    a.title.set_fontsize(8)
    a.legend(fontsize=7)
    for j in range(len(arrays["probes"]) + 1, cols):
        ax[1, j].axis("off")
    if title:
        fig.suptitle(title, fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path



def run(cfg: ShowConfig, command: str = "stride show", log=print) -> pathlib.Path:
    """Writes ``<out>/phase_portrait.png`` and ``<out>/phase.json``; returns the figure's path."""
    code = code_version()  # the code this process runs: read now, not when the result is written
    for path in (cfg.stride, cfg.baseline):
        if not runs.is_trained(pathlib.Path(path)):
            raise FileNotFoundError(f"no trained run at {path}: train it first (`stride train "
                                    f"--robot pendulum --model ... --out {path}`)")
    loaded = {"stride": runs.load_run(cfg.stride), "delan": runs.load_run(cfg.baseline)}
    names = {n: horizon.LABELS.get(n, n) for n in loaded}
    numbers, arrays = phase.evaluate(loaded, cfg.phase)
    out = pathlib.Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    fig = plot_phase(arrays, numbers, out / "phase_portrait.png",
                     f"Pendulum near the upright: MuJoCo vs STRIDE ({cfg.stride}) and DeLaN "
                     f"({cfg.baseline}); `{command}`")
    line = summary_line(numbers, names)
    atomic_write_text(out / "phase.json", json.dumps(
        {"command": command, "code": code, "config": dataclasses.asdict(cfg),
         "numbers": numbers, "summary": line}, indent=1))
    log(line)
    log(f"wrote {fig} (phase portrait: what the trained models predict near the upright)")
    return fig
