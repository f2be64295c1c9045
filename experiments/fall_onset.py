"""How the falls of a closed-loop scenario begin, from the traces the runs wrote: per episode,
when it fell, when the forward velocity first passed the command by more than ``--over`` m/s,
when the model-trust gate first handed the robot to the policy (``status`` DISTRUSTED) and the
share of upright steps it held it; a table (``OUT.md``, ``OUT.json``) and a figure (``OUT.png``:
forward velocity of every episode, fallen ones in red, one panel per part).

    python experiments/fall_onset.py results/closed_loop_g1_gpu/parts/new_lowf_gate \\
        results/closed_loop_g1_gpu/parts/new_lowf_overshoot --scenario low_friction \\
        --out results/closed_loop_g1_gpu/lowf_fall_onset

Traces (``trace_<scenario>_<model>[_seed<N>].npz``) are not tracked in git: the table and figure
are what stays.
"""

from __future__ import annotations

import argparse
import json
import pathlib

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from stride_jax import io  # noqa: E402
from stride_jax.control.mppi import DISTRUSTED  # noqa: E402
from stride_jax.jobs.closed_loop import trace_name  # noqa: E402
from stride_paper.seeds import kind_and_seed  # noqa: E402


def _first(t: np.ndarray, mask: np.ndarray) -> float | None:
    return float(t[mask.argmax()]) if mask.any() else None


def episodes(part: pathlib.Path, scenario: str, over: float) -> list[dict]:
    """One dict per row of ``part``'s ``closed_loop.json`` in ``scenario`` whose trace lies
    beside it."""
    rows = json.loads((part / "closed_loop.json").read_text())["rows"]
    out = []
    for r in rows:
        if r["scenario"] != scenario:
            continue
        seed = int(r.get("seed") or 0)
        path = part / trace_name(scenario, r["model"], int(r.get("episode", 0)), seed)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: the trace of {r['model']} (planner seed {seed}) "
                                    f"is missing; traces are not in git, only where the run wrote them")
        tr = np.load(path)
        t, up = tr["t"], ~tr["fallen"]
        ahead = tr["v_base"][:, 0] - tr["command"][:, 0]
        distrust = tr["status"] == DISTRUSTED
        out.append(dict(part=part.name, model=r["model"], kind=kind_and_seed(r)[0], seed=seed,
                        fell=bool(r["fell"]),
                        fall_s=_first(t, tr["fallen"]), over_s=_first(t, ahead > over),
                        distrust_s=_first(t, distrust),
                        distrust_share=float(distrust[up].mean()) if up.any() else 0.0,
                        t=t.tolist(), vx=tr["v_base"][:, 0].tolist()))
    return out


def _f(x) -> str:
    return "-" if x is None else f"{x:.2f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("parts", nargs="+", help="closed-loop run folders with their traces")
    ap.add_argument("--scenario", required=True)
    ap.add_argument("--over", type=float, default=0.15,
                    help="the forward overshoot of the command that marks an onset (m/s)")
    ap.add_argument("--out", required=True, help="output stem (.md, .json, .png)")
    a = ap.parse_args()
    eps = [e for p in a.parts for e in episodes(pathlib.Path(p), a.scenario, a.over)]
    if not eps:
        raise SystemExit(f"no rows of scenario {a.scenario!r} in {', '.join(a.parts)}")
    lines = [f"# How the falls begin: {a.scenario}", "",
             f"`python experiments/fall_onset.py {' '.join(a.parts)} --scenario {a.scenario} "
             f"--over {a.over} --out {a.out}`", "",
             f"Onset: the forward velocity first more than {a.over} m/s above the command. "
             "Gate: the first step the model-trust gate handed the robot to the policy; share: of "
             "the upright steps.", "",
             "| part | kind | episodes | fell | onset in the falls (s) | gate in the falls (s) | "
             "fall (s) | upright episodes with an onset |",
             "|---|---|---:|---:|---|---|---|---:|"]
    for part, kind in dict.fromkeys((e["part"], e["kind"]) for e in eps):
        mine = [e for e in eps if (e["part"], e["kind"]) == (part, kind)]
        falls = [e for e in mine if e["fell"]]
        span = lambda k: (", ".join(_f(e[k]) for e in falls) or "-")
        lines.append(f"| {part} | {kind} | {len(mine)} | {len(falls)} | {span('over_s')} | "
                     f"{span('distrust_s')} | {span('fall_s')} | "
                     f"{sum(e['over_s'] is not None for e in mine if not e['fell'])} of "
                     f"{len(mine) - len(falls)} |")
    lines += ["", "| part | model | planner seed | fell at (s) | onset (s) | gate (s) | "
              "gate share |", "|---|---|---:|---|---|---|---:|"]
    lines += [f"| {e['part']} | {e['model']} | {e['seed']} | {_f(e['fall_s'])} | "
              f"{_f(e['over_s'])} | {_f(e['distrust_s'])} | {e['distrust_share']:.2f} |"
              for e in eps]
    out = pathlib.Path(a.out)
    io.write_table(out, dict(scenario=a.scenario, over=a.over, parts=a.parts,
                             episodes=[{k: v for k, v in e.items() if k not in ("t", "vx")}
                                       for e in eps]),
                   "\n".join(lines) + "\n")
    parts = list(dict.fromkeys(e["part"] for e in eps))
    fig, axes = plt.subplots(1, len(parts), figsize=(5 * len(parts), 3.6), squeeze=False,
                             sharey=True)
    for ax, part in zip(axes[0], parts):
        for e in (e for e in eps if e["part"] == part):
            t, vx = np.asarray(e["t"]), np.asarray(e["vx"])
            keep = t <= (e["fall_s"] or t[-1])
            ax.plot(t[keep], vx[keep], color="tab:red" if e["fell"] else "0.6",
                    lw=1.2 if e["fell"] else 0.7)
            if e["distrust_s"] is not None and e["fell"]:
                ax.plot(e["distrust_s"], np.interp(e["distrust_s"], t, vx), "kx")
        ax.set(title=part, xlabel="t (s)", xlim=(0, 2.5))
    axes[0][0].set_ylabel("forward velocity (m/s); x: gate")
    fig.tight_layout()
    fig.savefig(out.with_suffix(".png"), dpi=120)
    print(f"wrote {out}.{{md,json,png}}")


if __name__ == "__main__":
    main()
