"""Why a planner's speed is off its command: its model, or its objective? (issue 19)

Along ``stride select-learned``'s validation episodes (the same flags, commands and planner
keys), every ``--every``-th control step, the planner's plan and each candidate group's
weighted mean (the plan-noise and policy-prior candidates, the policy's, the policy family's)
are replayed from the state the planner saw twice: through its model (with its disturbance
estimate, as its rollouts go) and through the simulator (``model_check.along``). Grouped by the
command (``select_learned.command_groups``), per group:

* **executed**: the base's forward speed minus the command at the recorded states (what the
  closed loop did);
* per sequence, the forward speed (mean over the horizon) **the model predicts** minus the
  command the planner tracks, and **the simulator's** minus it; their difference is the model's
  bias along what the planner chose. A planner with a velocity integral
  (``--planning.velocity-integral``) tracks the command moved against the integrated error:
  its sequences are read against that command, the executed speed against the one asked, and
  the table adds the move (the planner's command minus the asked one);
* each group's **weight** share, and the planner's objective (learned reward and value, read on
  either trajectory) of the family's mean minus the policy's: the preference as the model
  shows it and as the simulator's states would give it;
* **what the value reads**: its part of that preference beside the family's end state given
  one part of the policy's end state at a time (:data:`BLOCKS`: base velocity, orientation,
  joint positions, joint velocities; all of them give the policy's own end value), the value's
  change each swap makes.

Reading it: where the plan is faster than asked in the simulator but on the command in the
model, the model under-predicts the speed of what the planner picks (a model bias, the
observer's or a bias estimate's to answer); where the model predicts the speed too, the
planner picks speed on purpose: its objective prefers it (the reward and value's shape, what
relabelling answers). The per-episode means carry the intervals (90% t over episodes).

    python experiments/plan_bias.py --robot g1 --policy results/policies/ppo_g1_soft_ent \\
        --model stride=RUN --candidates soft=results/learned_g1_soft/reward_value.msgpack \\
        --worlds 8 --seconds 4 [the planner's --mppi.* and --planning.* flags] \\
        --every 5 --out results/planning_diagnosis/plan_bias_g1

Writes ``OUT/bias.{json,md}`` and ``OUT/bias.png`` (``--candidates``: one file, one planner).
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

SEQUENCES = ("plan", "prior", "policy", "family")  # what each recorded step replays
GROUPS = SEQUENCES[1:]  # the candidate groups, in MPPI's order
# parts of the family's end state given the policy's, one at a time, to read what the value
# scores in it (a floating base: q = [position 3, quaternion 4, joints], qd = [base 6, joints])
BLOCKS = ("base velocity", "orientation", "joint positions", "joint velocities", "all")


def swapped(q_fam, qd_fam, q_pol, qd_pol, block: str, nq: int):
    """The family's end state ``(q, qd)`` with ``block`` of the policy's (:data:`BLOCKS`; the base
    velocity is MuJoCo's free-joint velocity, the orientation the quaternion; ``all``: every
    part the value reads, so the policy's state but its position)."""
    q, qd = q_fam, qd_fam
    if block in ("base velocity", "all"):
        qd = qd.at[:6].set(qd_pol[:6])
    if block in ("orientation", "all"):
        q = q.at[3:7].set(q_pol[3:7])
    if block in ("joint positions", "all"):
        q = q.at[7:nq].set(q_pol[7:nq])
    if block in ("joint velocities", "all"):
        qd = qd.at[6:].set(qd_pol[6:])
    return q, qd


def recorder(cfg, env_cfg, policy):
    """``(planning, planner, sm, mx) -> record``: at a step, the plan and each candidate
    group's weighted mean replayed through the planner's model and the simulator (``mx``, the
    episodes' world)."""
    import jax.numpy as jnp

    from stride_jax.control import envs, model_check, planning as planning_lib

    def make(planning, planner, sm, mx):
        nq = sm.mj.nq
        mc = planning_lib.mppi_config(cfg.mppi, cfg.planning, planning)
        K, n_pol, n_fam = mc.samples, mc.policy_samples, mc.family_samples
        cut = [0, K - n_pol - n_fam, K - n_fam, K]  # prior | policy | family (MPPI's order)
        truth = planning_lib.make_planning(cfg.planning, env_cfg, sm,
                                           envs.mjx_step_fn(sm.n_substeps, mx), policy)
        value = planning.value or (lambda q, qd: jnp.zeros(()))

        def signals(q_aug, qd):  # forward, lateral (base frame), yaw rate
            a = planning_lib.split(q_aug, nq)
            v, w, _ = envs.base_signals(a.q, qd, a.gravity)
            return jnp.stack([v[0], v[1], w[2]])

        def record(q_aug, qd, u, info, q_next, qd_next, down, key):
            w = info.weights
            shares, means = [], []
            for lo, hi in zip(cut[:-1], cut[1:]):
                if hi > lo:
                    s = w[lo:hi].sum()
                    means.append(jnp.einsum("k,khu->hu", w[lo:hi] / jnp.maximum(s, 1e-12),
                                            info.candidates[lo:hi]))
                else:  # an empty group: its rows come back NaN
                    s = jnp.zeros(())
                    means.append(jnp.full_like(info.plan, jnp.nan))
                shares.append(s)
            a = planning_lib.split(q_aug, nq)
            # the simulator takes the state without the model's disturbance estimate
            q_true = planning_lib.augment(a.q, a.command, a.clock, a.gait, a.latched, None,
                                          a.gravity)
            seqs = jnp.stack([info.plan, *means])
            ok = jnp.all(jnp.isfinite(seqs), axis=(1, 2))
            got = model_check.along(planning.dynamics, truth.dynamics, planning.cost, value,
                                    signals, jnp.where(ok[:, None, None], seqs, 0.0), q_aug,
                                    q_true, qd, key)
            nan = lambda x: jnp.where(ok.reshape((-1,) + (1,) * (x.ndim - 1)), x, jnp.nan)
            # what the value reads: the family's end state with one part of the policy's
            fam, pol = SEQUENCES.index("family"), SEQUENCES.index("policy")
            swap = jnp.stack([jnp.stack([
                value(*swapped(got["end_q"][fam, side], got["end_qd"][fam, side],
                               got["end_q"][pol, side], got["end_qd"][pol, side], b, nq))
                - got["value"][fam, side] for side in (0, 1)]) for b in BLOCKS])
            swap = jnp.where(ok[fam] & ok[pol], swap, jnp.nan)  # [B, 2]
            return dict(track=nan(got["track"]), cost=nan(got["cost"]),
                        value=nan(got["value"]), swap=swap, share=jnp.stack(shares),
                        command=a.command, now=signals(q_aug, qd), down=down,
                        recorded=jnp.ones((), bool))

        return record

    return make


def summarise(rec: dict, commands, bounds, starts, settle_s: float, ctrl_dt: float) -> list[dict]:
    """Per command group (``select_learned.command_groups``): the recorded steps that count
    (recorded, upright, at least ``settle_s`` into their command), and over them the means and
    90% t-intervals over episodes (each episode's mean first) of what the module's docstring
    lists."""
    import numpy as np

    from stride_jax.jobs.select_learned import command_groups, paired

    W, T = np.asarray(rec["recorded"]).shape
    t = np.arange(T) * ctrl_dt
    starts = np.asarray(starts, float)
    piece = np.clip(np.searchsorted(starts, t + 1e-9, side="right") - 1, 0, len(starts) - 1)
    settled = t - starts[piece] >= settle_s - 1e-9
    counts = np.asarray(rec["recorded"], bool) & ~np.asarray(rec["down"], bool) & settled[None]
    cmd = np.asarray(rec["command"], float)  # [W, T, 3] as the planner tracked it
    asked = np.asarray(commands, float)[:, piece]  # [W, T, 3] as the episode asked it
    track = np.asarray(rec["track"], float)  # [W, T, S, 2, 3]
    cost = np.asarray(rec["cost"], float)  # [W, T, S, 2]
    value = np.asarray(rec["value"], float)  # [W, T, S, 2], the cost's terminal part
    swap = np.asarray(rec["swap"], float)  # [W, T, B, 2]
    share = np.asarray(rec["share"], float)  # [W, T, 3]
    now = np.asarray(rec["now"], float)  # [W, T, 3]
    out = []
    for label, in_group in command_groups(commands, bounds):
        m = counts & np.asarray(in_group, bool)[:, piece]  # [W, T]
        episodes = [i for i in range(W) if m[i].any()]

        def stat(x):  # x [W, T]: per-episode means over the group's steps, then over episodes
            per = [x[i][m[i]] for i in episodes]
            per = np.array([v[np.isfinite(v)].mean() for v in per if np.isfinite(v).any()])
            if not len(per):
                return None
            iv = paired(per, np.zeros(len(per)))
            return dict(mean=float(per.mean()), lo=None if iv is None else iv["lo"],
                        hi=None if iv is None else iv["hi"], n=len(per))

        g = dict(label=label, steps=int(m.sum()), episodes=len(episodes))
        if not episodes:
            out.append(g)
            continue
        g["executed_forward"] = stat(now[..., 0] - asked[..., 0])
        g["tracked_minus_asked"] = stat(cmd[..., 0] - asked[..., 0])  # a velocity integral's
        g["share"] = {k: stat(share[..., j]) for j, k in enumerate(GROUPS)}
        g["forward"] = {}
        for s, name in enumerate(SEQUENCES):
            g["forward"][name] = dict(model=stat(track[..., s, 0, 0] - cmd[..., 0]),
                                      true=stat(track[..., s, 1, 0] - cmd[..., 0]),
                                      bias=stat(track[..., s, 0, 0] - track[..., s, 1, 0]))
        fam, pol = SEQUENCES.index("family"), SEQUENCES.index("policy")
        g["cost_family_minus_policy"] = dict(model=stat(cost[..., fam, 0] - cost[..., pol, 0]),
                                             true=stat(cost[..., fam, 1] - cost[..., pol, 1]))
        # the terminal value's part of that difference (the cost subtracts the value)
        g["value_part"] = dict(model=stat(value[..., pol, 0] - value[..., fam, 0]),
                               true=stat(value[..., pol, 1] - value[..., fam, 1]))
        # the same sign: the value part each block alone carries
        g["value_swap"] = {b: dict(model=stat(swap[..., i, 0]), true=stat(swap[..., i, 1]))
                           for i, b in enumerate(BLOCKS)}
        out.append(g)
    return out


def _num(s: dict | None, interval: bool = False) -> str:
    if not s:
        return "n/a"
    if interval and s.get("lo") is not None:
        return f"{s['mean']:+.3f} [{s['lo']:+.3f}, {s['hi']:+.3f}]"
    return f"{s['mean']:+.3f}"


def markdown(table: dict) -> str:
    c = table["config"]
    # a velocity integral moves the command the planner tracks: its own column
    moved = any(g["episodes"] and g.get("tracked_minus_asked")
                and abs(g["tracked_minus_asked"]["mean"]) > 1e-6 for g in table["groups"])
    lines = ["# Where the planner's speed goes: its model's prediction against the simulator",
             "", f"Command: `{table['command']}` (code {table['code']})", "",
             f"{c['worlds']} validation episodes of {c['seconds']} s (`stride select-learned`'s, "
             f"seed {c['seed']}), planner model `{c['model']}`, learned reward/value "
             f"`{table['candidate']}`; every {table['every']} control steps the plan and each "
             "candidate group's weighted mean are replayed from the planner's state through its "
             "model and through the simulator (`experiments/plan_bias.py`). Forward speed (m/s, "
             "base frame, mean over the horizon) minus the command; + faster than asked. "
             "Means over episodes of each episode's mean over the group's steps, with 90% "
             "t-intervals over episodes where shown."
             + (" The planner tracked the asked command moved by its velocity integral "
                "(`--planning.velocity-integral`): the sequences' columns read against the "
                "command it tracked, the executed column against the one asked, and 'tracked "
                "minus asked' is the move." if moved else ""), "",
             "| commands | steps (episodes) | executed | "
             + ("tracked minus asked | " if moved else "")
             + "plan: model, simulator | plan: model minus simulator [90%] | policy cand.: "
             "model, simulator | family cand.: model, simulator | weight: prior, policy, family "
             "| objective, family minus policy: model, simulator | of which the terminal value: "
             "model, simulator |",
             "|---|---:|---:|" + ("---:|" if moved else "") + "---|" * 7]
    for g in table["groups"]:
        if not g["episodes"]:
            lines.append(f"| {g['label']} | 0 | | | | | | | | |" + (" |" if moved else ""))
            continue
        f = g["forward"]
        pair = lambda k: f"{_num(f[k]['model'])}, {_num(f[k]['true'])}"
        sh = ", ".join("n/a" if not g["share"][k] else f"{g['share'][k]['mean']:.2f}"
                       for k in GROUPS)
        cf, vp = g["cost_family_minus_policy"], g.get("value_part")
        lines.append(f"| {g['label']} | {g['steps']} ({g['episodes']}) | "
                     f"{_num(g['executed_forward'])} | "
                     + (f"{_num(g.get('tracked_minus_asked'))} | " if moved else "")
                     + f"{pair('plan')} | "
                     f"{_num(f['plan']['bias'], True)} | {pair('policy')} | {pair('family')} | "
                     f"{sh} | {_num(cf['model'])}, {_num(cf['true'])} | "
                     + (f"{_num(vp['model'])}, {_num(vp['true'])}" if vp else "n/a") + " |")
    lines += ["", "Objective: the planner's cost (learned reward's negative summed, minus the "
              "terminal value) of the family's weighted mean minus the policy's; negative: the "
              "family's plan is preferred; the terminal value's part is the policy's end value "
              "minus the family's (the rest is the running cost's)"
              + ("" if c.get("mppi", {}).get("discount", 1.0) == 1.0 else
                 "; read undiscounted, where the planner discounts by "
                 f"{c['mppi']['discount']:g}") + ". Replays are open loop from the state the "
              "planner saw; the closed loop replans every step, so they say what the planner "
              "expected of its choice, not what the episode did (the executed column says "
              "that)."]
    swaps = [g for g in table["groups"] if g["episodes"] and g.get("value_swap")]
    if swaps:
        lines += ["", "## What the value reads in the family's end state", "",
                  "The terminal value's part (as above: the policy's end value minus the "
                  "family's) and what each part of the policy's end state alone carries of it: "
                  "the family's end state given that part of the policy's, its value minus the "
                  "family's own, the same sign (`" + "`, `".join(BLOCKS[:-1]) + "`: MuJoCo's "
                  "free-joint velocity, the base quaternion, the joints; `all` of them: the "
                  "policy's state but its position, so the whole part). Model, simulator.", "",
                  "| commands | value's part | " + " | ".join(BLOCKS) + " |",
                  "|---|---|" + "---|" * len(BLOCKS)]
        for g in swaps:
            vp, sw = g["value_part"], g["value_swap"]
            lines.append(f"| {g['label']} | {_num(vp['model'])}, {_num(vp['true'])} | "
                         + " | ".join(f"{_num(sw[b]['model'])}, {_num(sw[b]['true'])}"
                                      for b in BLOCKS) + " |")
    return "\n".join(lines) + "\n"


def plot(out: pathlib.Path, groups: list[dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    groups = [g for g in groups if g["episodes"]]
    fig, ax = plt.subplots(figsize=(max(6.0, 1.4 * len(groups)), 3.6))
    x = np.arange(len(groups))
    bars = [("plan", "model"), ("plan", "true"), ("family", "model"), ("family", "true"),
            ("policy", "model"), ("policy", "true")]
    wdt = 0.8 / (len(bars) + 1)
    val = lambda s: np.nan if not s else s["mean"]
    for i, (seq, side) in enumerate(bars):
        ax.bar(x + i * wdt, [val(g["forward"][seq][side]) for g in groups], wdt,
               color=f"C{i // 2}", alpha=1.0 if side == "model" else 0.45,
               label=f"{seq}: {'model' if side == 'model' else 'simulator'}")
    ax.bar(x + len(bars) * wdt, [val(g["executed_forward"]) for g in groups], wdt, color="k",
           label="executed")
    ax.axhline(0, color="k", lw=0.6)
    ax.set_xticks(x + 0.4 - wdt / 2, [g["label"] for g in groups], rotation=20, ha="right",
                  fontsize=7)
    ax.set_ylabel("forward speed minus command (m/s)")
    ax.legend(fontsize=6, ncol=2)
    ax.grid(alpha=0.3, axis="y")
    fig.tight_layout()
    fig.savefig(out / "bias.png", dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> dict:
    stride_jax.set_xla_flags()
    from stride_jax.jobs.select_learned import PRESETS, SelectConfig

    argv = list(sys.argv[1:] if argv is None else argv)
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--preset", default="default", choices=list(PRESETS))
    config.add_flags(p, SelectConfig, skip=("policy_reference",), required=("out",))
    p.add_argument("--every", type=int, default=5,
                   help="replay at every this many control steps (from the first)")
    args = p.parse_args(argv)
    cfg = config.from_flags(SelectConfig, args, PRESETS[args.preset])
    command = shlex.join(["python", "experiments/plan_bias.py", *argv])
    return run(cfg, args.every, command)


def run(cfg, every: int, command: str, log=print) -> dict:
    import jax
    import numpy as np

    from stride_jax.control import learned as learned_lib
    from stride_jax.io import atomic_write_text, code_version
    from stride_jax.jobs import select_learned

    if every < 1:
        raise ValueError(f"every={every}: replay at every N >= 1 control steps")
    if cfg.sensor_noise > 0 or cfg.planning.latency_s > 0:
        raise ValueError("plan_bias pairs the planner's step with the true state as it acts: "
                         "no sensor noise, no latency")
    pairs = cfg.pairs()
    if len(pairs) != 1:
        raise ValueError(f"candidates: give one learned reward/value as LABEL=PATH (got "
                         f"{len(pairs)}; one run reads one planner)")
    label, path = pairs[0]
    if not pathlib.Path(path).is_file():
        raise FileNotFoundError(f"candidate {label}: no learned reward/value file at {path}")
    code = code_version()
    out = pathlib.Path(cfg.out)
    policy, env_cfg, starts, values, keys = select_learned.validation_commands(cfg)
    t0 = time.monotonic()
    progress = lambda s: log(f"  {s:.1f} of {cfg.seconds:g} s simulated "
                             f"({time.monotonic() - t0:.0f} s)")
    sm, episodes = select_learned.validation_episodes(cfg, policy, env_cfg, starts, progress,
                                                      recorder(cfg, env_cfg, policy), every)
    log(f"{label}: {cfg.worlds} episodes of {cfg.seconds:g} s, replaying every {every} steps")
    trace, rec = jax.block_until_ready(jax.jit(episodes)(learned_lib.load(path, ensemble=True),
                                                         values, keys))
    rec = jax.device_get(rec)
    bounds = [np.asarray(b).tolist() for b in env_cfg.commands.bounds()]
    groups = summarise(rec, np.asarray(values), bounds, starts, cfg.settle_s, sm.robot.ctrl_dt)
    table = dict(command=command, code=code, config=json.loads(json.dumps(
        dataclasses.asdict(cfg))), candidate=path, every=every, groups=groups,
        seconds=time.monotonic() - t0, falls=int(np.asarray(trace.fallen)[:, -1].sum()))
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "bias.json", json.dumps(table, indent=1))
    atomic_write_text(out / "bias.md", markdown(table))
    plot(out, groups)
    log(f"wrote {out / 'bias.md'} ({table['seconds']:.0f} s)")
    return table


if __name__ == "__main__":
    main()
