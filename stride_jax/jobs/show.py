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
import pathlib

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


def run(cfg: ShowConfig, command: str = "stride show", log=print) -> pathlib.Path:
    """Writes ``<out>/phase_portrait.png`` and ``<out>/phase.json``; returns the figure's path."""
    for path in (cfg.stride, cfg.baseline):
        if not runs.is_trained(pathlib.Path(path)):
            raise FileNotFoundError(f"no trained run at {path}: train it first (`stride train "
                                    f"--robot pendulum --model ... --out {path}`)")
    loaded = {"stride": runs.load_run(cfg.stride), "delan": runs.load_run(cfg.baseline)}
    names = {n: horizon.LABELS.get(n, n) for n in loaded}
    numbers, arrays = phase.evaluate(loaded, cfg.phase)
    out = pathlib.Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    fig = phase.plot(arrays, numbers, out / "phase_portrait.png",
                     f"Pendulum near the upright: MuJoCo vs STRIDE ({cfg.stride}) and DeLaN "
                     f"({cfg.baseline}); `{command}`")
    line = summary_line(numbers, names)
    atomic_write_text(out / "phase.json", json.dumps(
        {"command": command, "code": code_version(), "config": dataclasses.asdict(cfg),
         "numbers": numbers, "summary": line}, indent=1))
    log(line)
    log(f"wrote {fig} (phase portrait: what the trained models predict near the upright)")
    return fig
