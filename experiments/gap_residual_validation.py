"""Does early stopping on held-back trajectories help the STRIDE residual of the gap tool?

Plants an out-of-library effect in simulated Go1 (or pendulum) logs, diagnoses them with the
residual fitted on top ("always"), once training on every training trajectory and once with a
share held back for early stopping, and prints the held-out and training gap explained.

    python experiments/gap_residual_validation.py --robot go1 --effect '{"joint_stiffness": 10}' \\
        --trajectories 5 --steps 60 --preset fast
"""

import argparse
import dataclasses
import json

import stride_jax
from stride_jax.gap import diagnose, real, residual
from stride_jax.sim import model


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--robot", default="go1")
    p.add_argument("--effect", default='{"joint_stiffness": 10}')
    p.add_argument("--trajectories", type=int, default=5)
    p.add_argument("--steps", type=int, default=60)
    p.add_argument("--preset", default="fast")
    p.add_argument("--noise", action="store_true")
    p.add_argument("--validation", default="0,0.25")
    p.add_argument("--seed", type=int, default=1)
    a = p.parse_args()
    sm = model.load(a.robot)
    _, logged = real.generate(sm, json.loads(a.effect), a.trajectories, a.steps, a.seed,
                              real.SensorNoise() if a.noise else None)
    for v in map(float, a.validation.split(",")):
        cfg = dataclasses.replace(diagnose.PRESETS[a.preset], residual=residual.ResidualConfig(
            when="always", validation=v))
        res = diagnose.diagnose(sm, logged, cfg, log=lambda s: None)["residual"]
        es = res["early_stopping"]
        print(f"validation {v}: held-out {res['explained']:.1%} explained, train "
              f"{res['train_explained']:.1%}; step {es['chosen_step']} of {es['steps']} "
              f"({es['validation_trajectories']} trajectories held back)", flush=True)


if __name__ == "__main__":
    stride_jax.set_xla_flags()  # before JAX starts: small CPUs deadlock without
    main()
