"""One table of policies' margins: the falls of each policy alone, per scenario and action-noise
level, gathered from ``policy_noise.py``'s outputs named ``{robot}_{scenario}_{tag}_{policy}.json``
in one folder (``tag``: ``cpu64``, ``64``, ...; the policy label is the name's last part).

    python experiments/probes/policy_margins.py results/planning_diagnosis/slope_policies --robot g1 --tag cpu64 \
        --noise 0.001,0.01 --out results/planning_diagnosis/slope_policies/g1_margins_cpu64

Writes ``OUT.md`` and ``OUT.json``: a row per policy label, a column per scenario, each cell the
falls out of the draws at each of the ``--noise`` levels ("0 / 3 of 64" at 0.001 / 0.01; "?" for a
level that file did not run), "-" where that policy was not run in that scenario. The AR(1)
coefficient of every file must agree (a clear error otherwise): cells of different noises side by
side would read as one measure.
"""

from __future__ import annotations

import argparse
import json
import pathlib

from stride_jax.io import atomic_write_text


def gather(folder: pathlib.Path, robot: str, tag: str) -> dict:
    """``{policy: {scenario: {"noise": [...], "falls": [...], "draws": n, "command": ...}}}``."""
    out: dict = {}
    for f in sorted(folder.glob(f"{robot}_*_{tag}_*.json")):
        stem = f.stem[len(robot) + 1:]
        scenario, _, policy = stem.partition(f"_{tag}_")
        if not scenario or not policy:
            continue
        d = json.loads(f.read_text())
        rows = d["rows"]
        out.setdefault(policy, {})[scenario] = {
            "noise": [r["noise"] for r in rows], "falls": [r["falls"] for r in rows],
            "draws": rows[0]["draws"], "ar": d.get("ar", 0.0), "command": d.get("command", ""),
            "file": f.name}
    if not out:
        raise SystemExit(f"no {robot}_*_{tag}_*.json files in {folder}")
    return out


def table(data: dict, noise: list[float]) -> tuple[list[str], float, str]:
    """``(scenarios, AR(1) coefficient, markdown table)`` of :func:`gather`'s ``data`` at the
    ``noise`` levels."""
    scenarios = sorted({s for p in data.values() for s in p})
    ars = {c["ar"] for p in data.values() for c in p.values()}
    if len(ars) != 1:
        raise SystemExit(f"the files' AR(1) coefficients differ ({sorted(ars)}): one table holds one kind of noise")

    def falls(c, n):
        return next((str(f) for m, f in zip(c["noise"], c["falls"]) if abs(m - n) < 1e-12), "?")

    lines = ["| policy | " + " | ".join(scenarios) + " |", "|---|" + "---:|" * len(scenarios)]
    for policy in sorted(data):
        cells = []
        for s in scenarios:
            c = data[policy].get(s)
            cells.append("-" if c is None else " / ".join(falls(c, n) for n in noise) + f" of {c['draws']}")
        lines.append(f"| {policy} | " + " | ".join(cells) + " |")
    return scenarios, ars.pop(), "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder")
    ap.add_argument("--robot", default="g1")
    ap.add_argument("--tag", default="cpu64")
    ap.add_argument("--noise", default="0.001,0.01", help="the levels shown, comma-separated")
    ap.add_argument("--out", required=True, help="output stem (.md, .json)")
    a = ap.parse_args()
    noise = [float(x) for x in a.noise.split(",")]
    data = gather(pathlib.Path(a.folder), a.robot, a.tag)
    scenarios, ar, md = table(data, noise)
    levels = " / ".join(f"{n:g}" for n in noise)
    text = (f"# The {a.robot} policies alone: falls per scenario at action noise {levels} rad\n\n"
            f"`python experiments/probes/policy_margins.py {a.folder} --robot {a.robot} --tag {a.tag} "
            f"--noise {a.noise} --out {a.out}` (from each policy's `policy_noise.py` run, its command in the file named "
            f"below the table)\n\nEach cell: the episodes that fell at noise {levels} (AR(1) "
            f"coefficient {ar:g}), out of the draws.\n\n{md}\n\nFiles: "
            + ", ".join(f"`{c['file']}`" for p in data.values() for c in p.values()) + "\n")
    out = pathlib.Path(a.out)
    atomic_write_text(out.with_suffix(".md"), text)
    atomic_write_text(out.with_suffix(".json"), json.dumps(
        {"robot": a.robot, "tag": a.tag, "noise": noise, "ar": ar, "scenarios": scenarios,
         "policies": data}, indent=1))
    print(f"wrote {out}.{{md,json}}")


if __name__ == "__main__":
    main()
