"""Planner variants side by side on the same validation episodes: rows of ``stride
select-learned`` tables run with one seed, episode count and schedule (so the same commands and
planner keys) but other planner flags, each against the policy alone and against the first
variant, paired episode by episode, and where each gains or loses against the policy by command
(``select_learned.by_command``).

    python experiments/validation_variants.py "LABEL=DIR[:CANDIDATE]" ... --out FILE.md

DIR: a ``select-learned`` output folder (its ``selection.json``); CANDIDATE picks its row (the
best by default). The policy's reference row is read from the tables that carry one (they must
agree: the same episodes); tables whose commands differ are a clear error, not a comparison.
Writes ``FILE.md`` and ``FILE.json``."""

from __future__ import annotations

import argparse
import json
import pathlib
import shlex
import sys

from stride_jax.io import atomic_write_text
from stride_jax.jobs.select_learned import by_command, interval, versus

# what must match for two tables to have planned the same episodes
SAME_EPISODES = ("robot", "policy", "worlds", "seconds", "change_s", "settle_s", "seed")


def load(spec: str) -> tuple[str, dict, dict]:
    """``(label, row, table)`` of ``LABEL=DIR[:CANDIDATE]``."""
    label, _, where = spec.partition("=")
    if not (label and where):
        raise ValueError(f"{spec!r}: give LABEL=DIR[:CANDIDATE]")
    folder, _, name = where.partition(":")
    path = pathlib.Path(folder) / "selection.json"
    if not path.is_file():
        raise FileNotFoundError(f"{label}: no select-learned table at {path}")
    table = json.loads(path.read_text())
    rows = table["rows"]
    row = next((r for r in rows if r["label"] == name), None) if name else rows[0]
    if row is None:
        raise ValueError(f"{label}: {path} has no candidate {name!r} "
                         f"({', '.join(r['label'] for r in rows)})")
    return label, row, table


def compare(specs: list[str]) -> dict:
    """The variants' rows, each against the policy and the first variant, with their groups."""
    if not specs:
        raise ValueError("give at least one LABEL=DIR")
    loaded = [load(s) for s in specs]
    first = loaded[0][2]
    for label, _, table in loaded[1:]:
        for k in SAME_EPISODES:
            if table["config"].get(k) != first["config"].get(k):
                raise ValueError(f"{label}: {k}={table['config'].get(k)!r} where "
                                 f"{loaded[0][0]} has {first['config'].get(k)!r}: not the same "
                                 "episodes")
        if table.get("commands") != first.get("commands"):
            raise ValueError(f"{label}: its episodes' commands differ from {loaded[0][0]}'s")
    refs = [t["policy"] for _, _, t in loaded if t.get("policy")]
    for r in refs[1:]:
        if r["per_world"] != refs[0]["per_world"]:
            raise ValueError("the tables' policy rows differ on the same episodes: not one run's "
                             "episodes (another code or machine?)")
    policy = refs[0] if refs else None
    out = []
    for i, (label, row, table) in enumerate(loaded):
        out.append(dict(
            label=label, candidate=row["label"], vel_rmse=row["vel_rmse"], falls=row["falls"],
            worlds=row["worlds"], command=table["command"], code=row.get("code", table["code"]),
            vs_policy=versus(row, policy) if policy else None,
            vs_first=versus(row, loaded[0][1]) if i else None,
            where=by_command(row, policy, first["commands"], first["command_bounds"])
            if policy and first.get("command_bounds") else []))
    return dict(policy=None if policy is None else dict(vel_rmse=policy["vel_rmse"],
                                                        falls=policy["falls"]),
                variants=out, config={k: first["config"].get(k) for k in SAME_EPISODES})


def markdown(result: dict, command: str = "") -> str:
    v0 = result["variants"]
    c = result["config"]
    lines = ["# Planner variants on the same validation episodes", ""]
    if command:
        lines += [f"Command: `{command}`", ""]
    lines += [f"{c['worlds']} episodes of {c['seconds']} s ({c['robot']}, policy `{c['policy']}`, "
              f"a command every {c['change_s']} s, seed {c['seed']}); velocity RMSE (m/s), "
              "differences paired episode by episode with 90% t-intervals.", "",
              f"| variant | falls | velocity RMSE | minus the policy | minus {v0[0]['label']} |",
              "|---|---:|---:|---|---|"]
    p = result["policy"]
    if p is not None:
        lines.append(f"| the policy alone | {p['falls']} | {p['vel_rmse']:.4f} | | |")
    for v in v0:
        first = "-" if v["vs_first"] is None else interval(v["vs_first"])
        lines.append(f"| {v['label']} | {v['falls']} of {v['worlds']} | {v['vel_rmse']:.4f} | "
                     f"{interval(v['vs_policy'])} | {first} |")
    groups = [g["label"] for g in v0[0]["where"]]
    if groups:
        def cell(where, k):  # a variant's group: its interval, and which way it errs forward
            if not where:
                return "n/a"
            g = where[k]
            return interval(g["vel"]) + (f", fwd {g['forward'][0]:+.3f}" if "forward" in g
                                         else "")
        lines += ["", "Each variant minus the policy by command (each episode's error under each "
                  "command, velocity RMSE; the pieces taken as independent: a screen; fwd: the "
                  "variant's mean forward speed minus the command, m/s):", "",
                  "| commands | " + " | ".join(v["label"] for v in v0) + " |",
                  "|---|" + "---|" * len(v0)]
        for k, name in enumerate(groups):
            lines.append(f"| {name} ({v0[0]['where'][k]['n']}) | "
                         + " | ".join(cell(v["where"], k) for v in v0) + " |")
    lines += ["", "Commands per variant:", ""] + [f"- {v['label']}: `{v['command']}` "
                                                   f"(code {v['code']})" for v in v0]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("variants", nargs="+", help="LABEL=DIR[:CANDIDATE]")
    ap.add_argument("--out", required=True, help="FILE.md (FILE.json beside it)")
    a = ap.parse_args(argv)
    try:
        result = compare(a.variants)
    except (ValueError, FileNotFoundError) as e:
        raise SystemExit(f"validation_variants: error: {e}")
    out = pathlib.Path(a.out)
    command = "python experiments/validation_variants.py " + " ".join(
        shlex.quote(x) for x in (argv if argv is not None else sys.argv[1:]))
    atomic_write_text(out, markdown(result, command))
    atomic_write_text(out.with_suffix(".json"), json.dumps(dict(result, command=command),
                                                           indent=1))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
