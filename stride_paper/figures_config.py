"""What ``experiments/reproduce.py`` runs: its config, named presets and the parts it knows
(:mod:`stride_paper.figures` runs them)."""

from __future__ import annotations

import dataclasses

from stride_jax.dynamics import models as models_lib

PARTS = ("phase", "allocation", "nfe", "horizon", "forces")


@dataclasses.dataclass(frozen=True)
class ReproduceConfig:
    """What ``experiments/reproduce.py`` runs (lists are comma-separated strings).

    Attributes:
      root: data and runs folder (``<root>/data``, ``<root>/runs``, ``<root>/reproduce_cache``).
      out: figures and numbers folder.
      tag: run folder suffix (``<robot>-<tag>``); empty means the preset's name.
      parts: which of phase, allocation, nfe, horizon, forces.
      robots: legged robots of the horizon and forces parts (nfe is Go1's).
      models: legged models.
      seeds: legged seeds.
      train_legged: train missing legged runs here (else: evaluate what exists; make them with
        ``experiments/table1.py``).
      legged_episodes, legged_seconds: a legged dataset to generate when training here
        (seconds 0: the robot's default).
      legged_train_preset, legged_steps: ``stride train`` preset and steps of legged runs
        (steps 0: the preset's).
      pendulum_episodes, pendulum_seconds, pendulum_train_preset, pendulum_steps,
        pendulum_seeds: the same for the pendulum and bouncing-pendulum runs.
      horizon_tables: Table I files (``results/table1/<robot>/table.json``) to read the horizon
        part's errors from instead of evaluating runs: the same numbers Table I shows, every seed.
      horizon, windows, samples: rollout evaluation (steps, test windows, latent samples).
      nfe_flow, nfe_diffusion: NFE grids of the trade-off.
      timing_repeats: timed calls per inference rate (median).
      timing_batch: states per call of the batched inference rate.
      force_steps, force_window, force_samples: contact forces (steps per gait for the error,
        plotted steps, latent samples).
      phase_models: the pendulum models of the phase portrait.
      phase_grid, phase_worlds, phase_samples: phase portrait grid and draws per state.
      alloc_steps: held-out steps per region of the residual allocation.
      seed: evaluation draws.
    """

    root: str = "."
    out: str = "results/reproduce"
    tag: str = ""
    parts: str = ",".join(PARTS)
    robots: str = "go1,g1"
    models: str = ",".join(models_lib.MODELS)
    seeds: str = "0,1,2"
    train_legged: bool = False
    legged_episodes: int = 1024
    legged_seconds: float = 0.0
    legged_train_preset: str = "paper"
    legged_steps: int = 0
    pendulum_episodes: int = 512
    pendulum_seconds: float = 5.0
    pendulum_train_preset: str = "paper"
    pendulum_steps: int = 10000
    pendulum_seeds: str = "0,1,2"
    horizon_tables: str = ""
    horizon: int = 30
    windows: int = 256
    samples: int = 8
    nfe_flow: str = "1,2,4,8,16,32"
    nfe_diffusion: str = "1,2,4,8,16,32,64,100"
    timing_repeats: int = 20
    timing_batch: int = 256
    force_steps: int = 1024
    force_window: int = 100
    force_samples: int = 4
    phase_models: str = "onn,delan,stride"
    phase_grid: int = 21
    phase_worlds: int = 256
    phase_samples: int = 128
    alloc_steps: int = 2048
    seed: int = 0


PRESETS = {
    # CPU, CI-sized: every part end to end on tiny data and models (numbers are not the paper's).
    "tiny": ReproduceConfig(
        out="results/reproduce/tiny", seeds="0,1", train_legged=True, legged_episodes=8,
        legged_seconds=2.0, legged_train_preset="tiny", legged_steps=100, pendulum_episodes=24,
        pendulum_seconds=4.0, pendulum_train_preset="tiny", pendulum_steps=600,
        pendulum_seeds="0", windows=16, samples=2, nfe_flow="1,4", nfe_diffusion="1,4,10",
        timing_repeats=20, force_steps=64, force_window=40, force_samples=2, phase_grid=11,
        phase_worlds=32, phase_samples=16, alloc_steps=256),
    # GPU: legged runs from `experiments/table1.py --preset paper` under the same root; the
    # horizon part reads Table I's own numbers (every seed) from the committed tables.
    "paper": ReproduceConfig(
        out="results/reproduce/paper",
        horizon_tables="results/table1/go1/table.json,results/table1/g1/table.json"),
}
