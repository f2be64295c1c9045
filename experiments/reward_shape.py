"""Does the planner's learned cost want what the task wants? The learned reward and value
(``stride fit-reward-value``) against the environment's own reward, as the robot's forward
velocity moves away from the command, on the states of the policy's own episode.

Along the PPO policy's episode in a scenario (governed: the commands clipped to the policy's
training range, as the closed loop's ``--govern``), the states whose command is ``--command``
are taken, and each is evaluated with its base velocity shifted along the base's forward axis by
each of ``--shifts`` (m/s; everything else, the posture, the action, held): the learned reward
``r_hat(obs, a)`` (per control period, the units it was fitted in), the learned value ``V(obs)``,
the environment's reward of the state's terms (``envs.state_terms``; the action-rate, air-time
and foot-phase terms left out: they need the previous step or the feet's swing targets) and its
velocity-tracking part alone.
A cost that wants what the task wants falls as the velocity error grows, as the environment's
tracking reward does.

    python experiments/reward_shape.py --robot g1 --policy results/policies/ppo_g1_slope \\
        --learned results/learned_g1_slope/reward_value.msgpack --command 0,0,0 \\
        --out results/planning_diagnosis/g1_reward_shape_stop

Writes OUT.md and OUT.json.
"""

from __future__ import annotations

import argparse
import pathlib
import shlex
import sys

import numpy as np

import stride_jax


def shifted(q, qd, dv: float):
    """``qd`` with the base's linear velocity (world frame, MuJoCo's free joint) changed by
    ``dv`` m/s along the base's forward axis."""
    import jax.numpy as jnp

    from stride_jax.dynamics import integrate
    forward = integrate.quat_to_mat(q[3:7]) @ jnp.array([1.0, 0.0, 0.0], q.dtype)
    return qd.at[:3].add(dv * forward)


def main(argv: list[str] | None = None) -> dict:
    stride_jax.set_xla_flags()
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--robot", default="g1")
    ap.add_argument("--policy", required=True, help="the PPO policy's run folder")
    ap.add_argument("--learned", required=True, help="reward_value.msgpack")
    ap.add_argument("--scenario", default="changes")
    ap.add_argument("--command", default="0,0,0",
                    help="vx,vy,yaw rate: the states of the episode under this command")
    ap.add_argument("--shifts", type=float, nargs="+", default=[-0.4, -0.2, 0.0, 0.2, 0.4, 0.6])
    ap.add_argument("--out", required=True, help="path stem: writes OUT.md and OUT.json")
    a = ap.parse_args(argv)
    try:
        command = np.array([float(x) for x in a.command.split(",")])
    except ValueError:
        raise SystemExit(f"--command {a.command!r}: expected three numbers vx,vy,yaw") from None
    if command.shape != (3,):
        raise SystemExit(f"--command {a.command!r}: expected three numbers vx,vy,yaw")
    if not pathlib.Path(a.learned).is_file():
        raise SystemExit(f"--learned {a.learned}: no such file")

    import jax
    import jax.numpy as jnp

    from stride_jax.control import envs, learned as learned_lib
    from stride_jax.control.episode import policy_alone
    from stride_jax.control.planning import servo_torque, split
    from stride_jax.control.scenarios import SCENARIOS, governed
    from stride_jax.io import code_version, write_table
    from stride_jax.sim import model as sim_model
    from stride_jax.sim.rollout_mjx import fallen as is_fallen

    if a.scenario not in SCENARIOS:
        raise SystemExit(f"--scenario {a.scenario!r}: one of {sorted(SCENARIOS)}")
    sm = sim_model.load(a.robot)
    ep, env_cfg = policy_alone(sm, SCENARIOS[a.scenario], a.policy, govern=True)
    sc = governed(SCENARIOS[a.scenario], env_cfg.commands.bounds())  # what the episode ran
    nq, home, dt = sm.mj.nq, jnp.asarray(sm.info.qpos0[7:]), sm.robot.ctrl_dt
    cmds = np.asarray(jax.vmap(lambda qa: split(qa, nq).command)(jnp.asarray(ep.q_aug)))
    up = ~np.asarray(ep.fallen, bool)
    pick = np.flatnonzero(np.all(np.abs(cmds - command) < 1e-6, axis=1) & up)
    if not pick.size:
        raise SystemExit(f"no upright state of the policy's {sc.name!r} episode runs command "
                         f"{command.tolist()} (its commands: {sorted(set(map(tuple, cmds)))})")
    reward_p, value_p = learned_lib.load(a.learned, ensemble=True)  # as the planner reads it
    reward, value = learned_lib.reward_fn(reward_p), learned_lib.value_fn(value_p)
    cmd = jnp.asarray(command, jnp.float32)

    def evaluate(q_aug, qd, u, dv):
        s = split(q_aug, nq)
        qd = shifted(s.q, qd, dv)
        obs = envs.observe(env_cfg, home, s.q, qd, cmd, s.clock, s.gravity)
        act = (u - home) / env_cfg.action_scale
        r_hat = reward(obs, act)
        terms = envs.state_terms(env_cfg, home, s.q, qd, cmd, servo_torque(sm, s.q, qd, u),
                                 is_fallen(sm, s.q), s.gravity)
        _, parts = envs.total_reward(env_cfg, terms, dt)
        v, _, _ = envs.base_signals(s.q, qd, s.gravity)
        return (v[0], r_hat, value(obs), sum(parts.values()), parts["tracking_lin_vel"])

    run = jax.jit(jax.vmap(evaluate, in_axes=(0, 0, 0, None)))
    qa, qd, u = (jnp.asarray(x)[pick] for x in (ep.q_aug, ep.qd, ep.ctrl))
    rows = []
    for dv in a.shifts:
        vx, r_hat, v, env_r, track = (float(np.mean(x)) for x in run(qa, qd, u, dv))
        rows.append(dict(shift=dv, vx=vx, r_hat=r_hat, value=v, env_reward=env_r,
                         env_tracking=track))
    command_line = "python " + " ".join(map(shlex.quote, [sys.argv[0], *(argv or sys.argv[1:])]))
    stem = pathlib.Path(a.out)
    stem.parent.mkdir(parents=True, exist_ok=True)
    env = dict(command=command_line, code=code_version(), robot=a.robot, policy=a.policy,
               learned=a.learned, scenario=sc.name, governed_commands=sc.commands,
               asked=command.tolist(), states=int(pick.size))
    lines = [f"# The learned cost against the task's reward: {a.robot}, command "
             f"{command.tolist()}", "", f"Command: `{command_line}`", "",
             f"{pick.size} upright states of the policy's governed {sc.name!r} episode under "
             "that command, each with its base velocity shifted along the base's forward axis "
             "(posture and action held); means over the states. Learned reward and the "
             "environment's reward are per control period (dt times the scaled terms; the "
             "environment's without its action-rate, air-time and foot-phase terms); the value is "
             "the learned return from the state.", "",
             "| shift (m/s) | forward velocity (m/s) | learned reward | learned value | "
             "environment reward | its velocity tracking |", "|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['shift']:+.2f} | {r['vx']:+.3f} | {r['r_hat']:+.4f} | "
                     f"{r['value']:+.3f} | {r['env_reward']:+.4f} | {r['env_tracking']:+.4f} |")
    write_table(stem, dict(env=env, rows=rows), "\n".join(lines) + "\n")
    print("\n".join(lines[-len(rows) - 2:]))
    print(f"wrote {stem}.{{md,json}}")
    return dict(rows=rows)


if __name__ == "__main__":
    main()
