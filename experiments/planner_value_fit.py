"""The value refit on a closed-loop planner's own rollouts, for any planner the closed loop runs
(issue 19, Dreamer-MPC's value; :func:`stride_jax.jobs.dreamer_mpc.train_value`).

The Dreamer-MPC ablation (``stride_jax.jobs.dreamer_mpc``) refits the value with one of its own
variants' planners; this takes the closed loop's flags instead (``--robot``, ``--models
NAME=RUN``, ``--policy``, ``--learned``, ``--mppi.*``, ``--planning.*``: the planner a
``select-learned`` or ``closed-loop`` run plans with) and the collection's and fit's
(``--value.worlds``, ``--value.seconds``, ``--value.rounds`` ...): that planner drives the MJX
robot on the nominal ground under commands of the policy's distribution, and the value is
refitted from ``--learned``'s on what it visited and on its candidates' imagined rollouts,
with the planner's own running cost as the reward (:mod:`stride_jax.control.planner_value`).
The closed loop's scenario flags (``--seconds``, ``--episodes``, the terrain's) do not apply:
the collection runs ``--value.worlds`` episodes of ``--value.seconds`` on the nominal ground.
Writes ``OUT/reward_value.msgpack`` (the same reward, the new value: a drop-in ``--learned`` or
``--candidates`` file), ``error_model.msgpack`` and ``report.json``:

    python experiments/planner_value_fit.py --robot g1 --models stride=RUN \\
        --policy results/policies/ppo_g1_soft_ent --learned results/learned_g1_soft/reward_value.msgpack \\
        [the planner's --mppi.* and --planning.* flags] --value.worlds 8 --value.seconds 4 --out DIR
"""

from __future__ import annotations

import argparse
import dataclasses
import shlex
import sys

import stride_jax
from stride_jax import config
from stride_jax.control.planner_value import PlannerValueConfig


@dataclasses.dataclass(frozen=True)
class ValueFlags:
    """The collection and fit (``--value.*``).

    Attributes:
      value: the planner's data and the refit
        (:class:`~stride_jax.control.planner_value.PlannerValueConfig`).
    """

    value: PlannerValueConfig = PlannerValueConfig()


def parse(argv: list[str]):
    """``(closed-loop config, value config, out)`` of the command line."""
    from stride_jax.jobs.closed_loop import PRESETS, ClosedLoopConfig

    p = argparse.ArgumentParser(prog="experiments/planner_value_fit.py",
                                description=__doc__.split("\n")[0])
    config.add_flags(p, ClosedLoopConfig, skip=("out", "scenarios"))
    config.add_flags(p, ValueFlags)
    p.add_argument("--out", required=True, help="folder for the refit value and its report")
    args = p.parse_args(argv)
    cl = config.from_flags(ClosedLoopConfig, args, PRESETS["default"])
    vf = config.from_flags(ValueFlags, args, ValueFlags())
    models = [m for m in cl.models.split(",") if m]
    if len(models) != 1 or "=" not in models[0]:
        raise SystemExit(f"--models: give the one learned model the planner plans through, "
                         f"NAME=RUN (got {cl.models!r})")
    if not (cl.policy and cl.learned):
        raise SystemExit("--policy and --learned: the planner's value starts from a learned "
                         "reward and value and plans with the policy's candidates")
    return dataclasses.replace(cl, out=args.out), vf.value, args.out


def main(argv: list[str] | None = None) -> dict:
    stride_jax.set_xla_flags()
    argv = list(sys.argv[1:] if argv is None else argv)
    cl, vcfg, out = parse(argv)
    from stride_jax.jobs import dreamer_mpc

    name, _, run = cl.models.partition("=")
    command = shlex.join(["python", "experiments/planner_value_fit.py", *argv])
    return dreamer_mpc.train_value(cl, vcfg, name, run, out, command)


if __name__ == "__main__":
    main()
