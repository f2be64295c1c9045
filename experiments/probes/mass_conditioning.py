"""How well conditioned is a structured model's mass matrix along the policy's episode in a
scenario, and how far apart are the CPU's and the GPU's float32 solves of ``M qdd = f`` there?

The closed loop solves ``M(q) qdd = f`` in float32 by Gauss-Jordan elimination on a CPU and by
cuSOLVER's Cholesky elsewhere (``stride_jax.dynamics.linalg.spd_solve``); both lose about
``cond(M) * 1e-7`` of relative accuracy. Per model: cond(M) (median, 95th percentile, max) over
the episode's states, and each float32 solver's relative error against a float64 solve with the
right-hand side ``M @ qdd`` of the episode's observed accelerations.

    python experiments/probes/mass_conditioning.py --robot g1 --scenario tilt --slope-deg 15 \\
        --models stride=results/models/g1_walk_tw1_tf0.25_b/stride-s0,...
"""

from __future__ import annotations

import argparse
import dataclasses
import pathlib
import sys

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
import stride_jax  # noqa: E402


def main(argv=None) -> None:
    stride_jax.set_xla_flags()
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--robot", default="g1")
    ap.add_argument("--scenario", default="tilt")
    ap.add_argument("--slope-deg", type=float, default=0.0)
    ap.add_argument("--seconds", type=float, default=6.0)
    ap.add_argument("--models", required=True)
    a = ap.parse_args(argv)

    import jax
    import jax.numpy as jnp

    from experiments.scenario_model_error import episode
    from stride_jax.control.episode import learned_model
    from stride_jax.control.scenarios import SCENARIOS
    from stride_jax.dynamics import linalg, physics
    from stride_jax.sim import model as sim_model

    sm = sim_model.load(a.robot)
    sc = dataclasses.replace(SCENARIOS[a.scenario], seconds=a.seconds)
    if a.slope_deg:
        sc = dataclasses.replace(sc, name=f"{sc.name}{a.slope_deg:g}", slope_deg=a.slope_deg)
    t, q, qd, _, _, qd2, fallen = episode(sm, sc, f"results/policies/ppo_{a.robot}")
    n = int(np.argmax(fallen)) if fallen.any() else len(t)
    q, qd, qd2 = q[:n], qd[:n], qd2[:n]
    qdd = (qd2 - qd) / sm.robot.ctrl_dt
    print(f"{a.robot} {sc.name}: {n} states of the policy's episode")
    print("| model | cond(M) median | 95th pct | max | Gauss-Jordan (CPU) rel. err median / max "
          "| Cholesky (GPU) rel. err median / max |")
    print("|---|---:|---:|---:|---|---|")
    for spec in [m for m in a.models.split(",") if m]:
        name, run = spec.split("=", 1)
        model, params = learned_model(run, sm)
        M = np.asarray(jax.jit(jax.vmap(lambda x: physics.mass_matrix(model, params, x)))(q))
        M64 = M.astype(np.float64)
        cond = np.linalg.cond(M64)
        b64 = np.einsum("tij,tj->ti", M64, qdd)
        x64 = np.linalg.solve(M64, b64[..., None])[..., 0]
        Mf, bf = jnp.asarray(M, jnp.float32), jnp.asarray(b64, jnp.float32)
        gj = np.asarray(jax.jit(jax.vmap(linalg._gauss_jordan, in_axes=(0, 0)))(Mf, bf))
        ch = np.asarray(jax.jit(jax.vmap(linalg._solve_cholesky))(Mf, bf))

        scale = np.maximum(np.linalg.norm(x64, axis=-1), 1e-12)
        e_gj, e_ch = (np.linalg.norm(x - x64, axis=-1) / scale for x in (gj, ch))
        print(f"| {name} | {np.median(cond):.3g} | {np.percentile(cond, 95):.3g} | "
              f"{cond.max():.3g} | {np.median(e_gj):.2g} / {e_gj.max():.2g} | "
              f"{np.median(e_ch):.2g} / {e_ch.max():.2g} |", flush=True)


if __name__ == "__main__":
    main()
