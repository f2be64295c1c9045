"""One table from ``experiments/scenario_model_error.py`` runs of the same models along two
policies' episodes (``<scenario>_<policy>.json`` in one folder): per scenario and policy, each
model kind's mean over its trained seeds of the one-period joint-velocity RMSE and of the base
acceleration's spread (both from the split on), and ONN minus STRIDE.

    python experiments/probes/policy_shift_table.py results/planning_diagnosis/g1_policy_shift ppo_g1,ppo_g1_slope
"""
import json
import pathlib
import sys

import numpy as np

from stride_jax import io
from stride_paper.seeds import kind_and_seed

folder, policies = pathlib.Path(sys.argv[1]), sys.argv[2].split(",")

def split(stem: str) -> tuple[str, str] | None:
    """``(scenario, policy)`` of a run's file stem: the longest policy name it ends with."""
    pol = max((q for q in policies if stem.endswith("_" + q)), key=len, default=None)
    return (stem[:-len(pol) - 1], pol) if pol else None


scenarios = list(dict.fromkeys(s[0] for p in sorted(folder.glob("*.json")) if (s := split(p.stem))))
lines = [f"# One-period model error along each policy's own episode ({folder.name})", "",
         f"`python experiments/probes/policy_shift_table.py {folder} {sys.argv[2]}`; the runs' commands "
         "are in each `<scenario>_<policy>.md`. Mean over trained seeds, from the split on "
         "(joint-velocity RMSE after one control period, rad/s; spread of the base's linear "
         "acceleration error around its bias, m/s^2).", "",
         "| scenario | policy | STRIDE joints | ONN joints | STRIDE spread | ONN spread |",
         "|---|---|---:|---:|---:|---:|"]
for sc in scenarios:
    for pol in policies:
        p = folder / f"{sc}_{pol}.json"
        if not p.is_file():
            continue
        rows = json.loads(p.read_text())["rows"]
        phase = [k for k in rows[0] if k.startswith("from ")][0]
        agg = {}
        for r in rows:
            if r.get("told_gravity"):
                continue
            k = kind_and_seed(r)[0]
            agg.setdefault(k, []).append((r[phase]["joint_vel_rmse"], r[phase]["spread_norm"]))
        m = {k: np.mean(v, axis=0) for k, v in agg.items()}
        cell = lambda k, i: f"{m[k][i]:.3f}" if k in m else "-"
        lines.append(f"| {sc} | {pol} | {cell('stride', 0)} | {cell('onn', 0)} | {cell('stride', 1)} | "
                     f"{cell('onn', 1)} |")
out = folder / "summary.md"
io.atomic_write_text(out, "\n".join(lines) + "\n")
print(out.read_text())
