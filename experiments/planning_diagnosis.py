"""Why planning through a learned model can make the policy worse (issue 19, item 1).

Along the PPO policy's own closed-loop episode in each scenario, at every ``--every``-th control
step, the MPPI planner of each learned model proposes its candidates; they are replayed in the
scenario's MJX model from the same state (``stride_jax.control.model_check``): the model's error
along them, its cost bias, how well it ranks them, and the regret of its weights. Also the
policy's own action spread against the planner's exploration noise. Writes ``diagnosis.json``,
``diagnosis.md`` and ``errors.png`` to ``--out``.

    python experiments/planning_diagnosis.py --preset tiny --out /tmp/diag           # CPU, minutes
    python experiments/planning_diagnosis.py --preset gpu --out results/planning_diagnosis
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib
import shlex
import sys
import time

import stride_jax
from stride_jax import config

MODELS = "stride=results/models/go1/stride-s0,delan=results/models/go1/delan-s0," \
         "onn=results/models/go1/onn-s0"


@dataclasses.dataclass(frozen=True)
class DiagnosisConfig:
    """What the diagnosis replays (the defaults are the ``cpu`` preset).

    Attributes:
      robot: the robot.
      models: NAME=RUN,... (trained dynamics models).
      scenarios: comma-separated closed-loop scenarios.
      policy: the PPO run whose closed loop is diagnosed (and whose candidates are planned).
      learned: learned reward/value ('' for the analytic cost).
      samples, horizon, policy_samples: the planner (``MPPIConfig``'s).
      seconds: the policy's episode per scenario (s).
      every: diagnose every this many control steps.
      central: comma-separated names of ``models`` that plan with their residual's central
        sample (``key=None`` at every step, as ``MPPIConfig(latents="central")``), e.g.
        ``stride_central=RUN`` beside ``stride=RUN`` compares the two on the same states.
      model_gravity: the planner tells its model the sensed gravity direction
        (``PlanningConfig.model_gravity``, as the closed loop's ``--planning.model-gravity``;
        models trained on sloped data).
      split_s: comma-separated times (s) that cut the episode into windows: one row per model
        and window besides the whole episode (e.g. ``2``: the first two seconds apart).
      out: results folder.
    """

    robot: str = "go1"
    models: str = MODELS
    scenarios: str = "slope,rough,changes"
    policy: str = "results/policies/ppo_go1"
    learned: str = "results/learned_go1/reward_value.msgpack"
    samples: int = 128
    horizon: int = 20
    policy_samples: int = 16
    seconds: float = 3.0
    every: int = 15
    central: str = ""
    model_gravity: bool = False
    split_s: str = ""
    out: str = "results/planning_diagnosis"


PRESETS = {
    "tiny": DiagnosisConfig(samples=16, horizon=4, policy_samples=4, seconds=0.6, every=10,
                            scenarios="slope"),
    "cpu": DiagnosisConfig(),
    "gpu": DiagnosisConfig(samples=1024, horizon=20, policy_samples=64, seconds=6.0, every=10),
}


def main(argv: list[str] | None = None) -> dict:
    stride_jax.set_xla_flags()
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--preset", default="cpu", choices=list(PRESETS))
    config.add_flags(p, DiagnosisConfig)
    args = p.parse_args(argv)
    cfg = config.from_flags(DiagnosisConfig, args, PRESETS[args.preset])
    command = "python " + " ".join(map(shlex.quote, [sys.argv[0], *(argv or sys.argv[1:])]))
    return run(cfg, command)


def run(cfg: DiagnosisConfig, command: str) -> dict:
    import jax
    import jax.numpy as jnp
    import numpy as np

    from stride_jax.control import envs, learned as learned_lib, model_check, mppi, ppo
    from stride_jax.control.episode import learned_step_fn, policy_episode, scenario_world
    from stride_jax.control.planning import (PlanningConfig, make_planner, make_planning,
                                             mppi_config)
    from stride_jax.control.scenarios import SCENARIOS
    from stride_jax.io import atomic_write_text, code_version
    from stride_jax.sim import model as sim_model

    out = pathlib.Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    sm = sim_model.load(cfg.robot)
    nu = sm.info.nu
    policy, _, env_cfg = ppo.load_policy(cfg.policy)
    # ensembles read as the closed loop reads them
    learned = learned_lib.load(cfg.learned, ensemble=True) if cfg.learned else None
    mppi_cfg = mppi.MPPIConfig(samples=cfg.samples, horizon=cfg.horizon,
                               policy_samples=cfg.policy_samples)
    planning_cfg, seed = PlanningConfig(model_gravity=cfg.model_gravity), 0  # the closed loop's defaults
    cuts = sorted(float(x) for x in cfg.split_s.split(",") if x.strip())
    models = [tuple(m.split("=", 1)) for m in cfg.models.split(",") if m]
    steps = {name: learned_step_fn(run_dir, sm) for name, run_dir in models}
    for name in [n for n in cfg.central.split(",") if n]:
        if name not in steps:
            raise ValueError(f"central: {name!r} is not one of the models {sorted(steps)}")
        steps[name] = (lambda f: lambda q, qd, ctrl, key: f(q, qd, ctrl, None))(steps[name])
    rows, t_start = [], time.time()
    jitted = {}  # one program per model and scenario structure (the MJX model is an argument)

    def checker(name, slots_sig):
        """``(mx, q_aug [S, ...], qd [S, nv], keys [S]) -> per-state comparison`` for ``name``."""
        if (name, slots_sig) in jitted:
            return jitted[name, slots_sig]
        planning = make_planning(planning_cfg, env_cfg, sm, steps[name], policy, learned)
        with jax.ensure_compile_time_eval():
            planner = make_planner(planning, mppi_config(mppi_cfg, planning_cfg, planning))
        H = mppi_cfg.horizon

        def at(mx, q, v, key):
            truth = make_planning(planning_cfg, env_cfg, sm, envs.mjx_step_fn(sm.n_substeps, mx),
                                  policy, learned)
            st = planner.init(key, jnp.broadcast_to(jnp.asarray(planning.nominal_u),
                                                    (H, len(planning.lo))))
            _, _, info = planner.step(st, q, v)
            return model_check.one_state(planning.dynamics, truth.dynamics, planning.cost,
                                         planning.value or (lambda q, qd: jnp.zeros(())),
                                         info.candidates, q, v, key, mppi_cfg.temperature, nu)

        jitted[name, slots_sig] = jax.jit(jax.vmap(at, in_axes=(None, 0, 0, 0)))
        return jitted[name, slots_sig]

    for sc_name in [s for s in cfg.scenarios.split(",") if s]:
        sc = dataclasses.replace(SCENARIOS[sc_name], seconds=cfg.seconds)
        world = scenario_world(sm, sc, seed)
        mx = world.mx
        truth = make_planning(planning_cfg, env_cfg, sm, envs.mjx_step_fn(sm.n_substeps, mx),
                              policy, learned)
        ep = policy_episode(world, truth)
        q_aug, qd, actions = ep.q_aug, ep.qd, ep.u
        n_steps = len(ep.t)
        pick = np.arange(cfg.every, n_steps, cfg.every)
        spread = float(np.asarray(actions).std(axis=0).mean())
        sig = (tuple(envs.contact_slots(mx)[0]), mx.opt.timestep.shape,
               jax.tree.structure(mx))
        for name, _ in models:
            t0 = time.time()
            per = checker(name, sig)(mx, q_aug[pick], qd[pick],
                                     jax.random.split(jax.random.key(seed), len(pick)))
            per = jax.device_get(per)
            seconds = time.time() - t0
            t_pick = np.asarray(ep.t)[pick]
            edges = [0.0, *cuts, np.inf]
            windows = [("all", np.ones(len(pick), bool))] + ([
                (f"{a:g}-{b:g} s" if np.isfinite(b) else f"{a:g} s-", (t_pick >= a) & (t_pick < b))
                for a, b in zip(edges[:-1], edges[1:])] if cuts else [])
            for window, m in windows:
                if not m.any():
                    continue
                row = dict(scenario=sc_name, model=name, window=window, seconds=seconds,
                           policy_action_std=spread, noise_std=planning_cfg.noise_std,
                           **model_check.summarise(jax.tree.map(lambda a: a[m], per),
                                                   mppi_cfg.policy_samples))
                rows.append(row)
                print(f"{sc_name:>8} {name:>6} {window:>7}: rank corr {row['spearman']:.2f}, top-10% "
                      f"overlap {row['top10_overlap']:.2f}, regret {row['regret']:.3f}, cost bias "
                      f"{row['cost_bias_mean']:.3f} (true spread {row['cost_true_spread']:.3f}), "
                      f"vel err at H {row['vel_err_noise'][-1]:.3f} m/s, plan forward bias "
                      f"{np.mean(row['plan_fwd_bias']):+.3f} m/s ({seconds:.0f} s)", flush=True)
            env = dict(command=command, backend=jax.default_backend(),
                       device=jax.devices()[0].device_kind, code=code_version(),
                       config=dataclasses.asdict(cfg), models=dict(models), policy=cfg.policy,
                       learned=cfg.learned)
            atomic_write_text(out / "diagnosis.json", json.dumps(dict(env=env, rows=rows),
                                                                 indent=1))
    write_md(out, rows, command, cfg)
    plot(out, rows)
    print(f"wrote {out / 'diagnosis.md'} ({time.time() - t_start:.0f} s)")
    return dict(rows=rows)


def write_md(out: pathlib.Path, rows: list[dict], command: str, cfg: DiagnosisConfig) -> None:
    from stride_jax.io import atomic_write_text

    lines = ["# Planning through learned models: candidates replayed in the simulator", "",
             f"Command: `{command}`", "",
             f"K={cfg.samples}, H={cfg.horizon}, {cfg.policy_samples} policy "
             f"candidates; states every {cfg.every} control steps of the policy's own "
             f"{cfg.seconds} s episode per scenario (`stride_jax/control/model_check.py`).",
             "", "Forward bias: the model's predicted forward velocity (m/s, in the base's heading "
             "at the state) minus the true one, along the plan its weights make (mean over the "
             "horizon) and along the candidates at the horizon's end; negative: the model "
             "expects less speed than the plan reaches.",
             "", "| scenario | model | window | states | rank corr | top-10% overlap | regret | cost bias (noise "
             "/ policy cand.) | true cost spread | vel err at H, noise / policy cand. (m/s) | "
             "joint err at H (rad) | forward bias: plan / noise / policy cand. at H (m/s) | "
             "policy action std / noise std (rad) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    f = lambda x: "-" if x is None else f"{x:.3f}"
    for r in rows:
        lines.append(
            f"| {r['scenario']} | {r['model']} | {r.get('window', 'all')} | {r['states']} | "
            f"{r['spearman']:.2f} | {r['top10_overlap']:.2f} | "
            f"{f(r['regret'])} | {f(r.get('cost_bias_noise', r['cost_bias_mean']))} / "
            f"{f(r.get('cost_bias_policy'))} | {f(r['cost_true_spread'])} | "
            f"{f(r['vel_err_noise'][-1])} / "
            f"{f((r.get('vel_err_policy') or [None])[-1])} | {f(r['joint_err_noise'][-1])} | "
            f"{_signed(r.get('plan_fwd_bias'), True)} / {_signed(r.get('fwd_bias_noise'))} / "
            f"{_signed(r.get('fwd_bias_policy'))} | "
            f"{r['policy_action_std']:.3f} / {r['noise_std']:.3f} |")
    atomic_write_text(out / "diagnosis.md", "\n".join(lines) + "\n")


def _signed(series: list | None, mean: bool = False) -> str:
    """A forward-bias series' mean (``mean``) or last value, signed; ``-`` where the row has
    none (rows written before it existed)."""
    if not series:
        return "-"
    return f"{(sum(series) / len(series) if mean else series[-1]):+.3f}"


def plot(out: pathlib.Path, rows: list[dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenarios = list(dict.fromkeys(r["scenario"] for r in rows))
    fig, axes = plt.subplots(1, len(scenarios), figsize=(4.5 * len(scenarios), 3.5),
                             squeeze=False)
    for ax, sc in zip(axes[0], scenarios):
        for i, r in enumerate(x for x in rows if x["scenario"] == sc and x.get("window", "all") == "all"):
            h = range(1, len(r["vel_err_noise"]) + 1)
            ax.plot(h, r["vel_err_noise"], color=f"C{i}", label=f"{r['model']}: noise cand.")
            if r.get("vel_err_policy"):
                ax.plot(h, r["vel_err_policy"], color=f"C{i}", ls="--",
                        label=f"{r['model']}: policy cand.")
        ax.set(title=sc, xlabel="horizon step", ylabel="base velocity error (m/s)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "errors.png", dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
