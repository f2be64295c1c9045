"""Closed-loop tracking error per command segment: where in a command schedule a controller loses.

    python experiments/command_segments.py "policy=PART/trace_changes_policy*.npz" \\
        "stride=PART/trace_changes_stride*.npz" --out results/x/changes_segments

Each ``LABEL=GLOB`` names the saved traces of one controller (``trace_*.npz`` beside a closed-loop
run: one per planner draw). A segment is a stretch of constant command, read off the traces
themselves (every trace of a table must share the schedule); its error is the velocity RMSE over
the steps the closed loop scores (``stride_jax.control.episode.tracked``: upright, 0.5 s or more
after the latest change), the whole episode's is the closed loop's own ``vel_rmse``. Per label:
the mean over its draws. Writes ``OUT.md`` and ``OUT.json``.
"""

from __future__ import annotations

import argparse
import glob
from types import SimpleNamespace

import numpy as np

from stride_jax import io
from stride_jax.control import episode


def load(path: str) -> SimpleNamespace:
    with np.load(path) as d:
        return SimpleNamespace(**{k: d[k] for k in ("t", "command", "v_base", "fallen")})


def segments(trace) -> list[tuple[float, float, np.ndarray]]:
    """``(start s, end s, command [3])`` of each stretch of constant command."""
    t, c = np.asarray(trace.t), np.asarray(trace.command)
    starts = np.flatnonzero(np.r_[True, np.any(np.diff(c, axis=0) != 0, axis=1)])
    ends = np.r_[starts[1:], len(t)]
    dt = float(t[1] - t[0]) if len(t) > 1 else 0.0
    return [(float(t[a]), float(t[b - 1]) + dt, c[a]) for a, b in zip(starts, ends)]


def errors(trace, settle_s: float = 0.5) -> tuple[list[float], float]:
    """The velocity RMSE over the scored steps of each segment (NaN: none scored), and overall."""
    t = np.asarray(trace.t)
    use = episode.tracked(trace, settle_s)
    e2 = np.sum((np.asarray(trace.v_base)[:, :2] - np.asarray(trace.command)[:, :2]) ** 2, axis=1)
    rmse = lambda m: float(np.sqrt(e2[m].mean())) if m.any() else float("nan")
    per = [rmse(use & (t >= a) & (t < b)) for a, b, _ in segments(trace)]
    return per, rmse(use)


def _mean(x: np.ndarray) -> float:
    """The mean of the finite values (NaN: none, e.g. every draw fell before the segment)."""
    x = x[np.isfinite(x)]
    return float(x.mean()) if len(x) else float("nan")


def table(groups: dict[str, list[str]]) -> dict:
    """Per label: its draws' per-segment and whole-episode errors (their means) and falls."""
    schedule, rows = None, []
    for label, paths in groups.items():
        if not paths:
            raise SystemExit(f"{label}: no trace matches")
        per, whole, fell = [], [], 0
        for p in paths:
            tr = load(p)
            fell += bool(np.asarray(tr.fallen).any())
            seg = segments(tr)
            key = [(round(a, 6), [round(float(x), 6) for x in c]) for a, _, c in seg]
            if schedule is None:
                schedule = (key, seg)
            elif key != schedule[0]:
                raise SystemExit(f"{p}: its command schedule differs from the first trace's")
            s, w = errors(tr)
            per.append(s)
            whole.append(w)
        per = np.asarray(per)
        rows.append(dict(label=label, draws=len(paths), files=sorted(paths),
                         segments=[_mean(per[:, j]) for j in range(per.shape[1])],
                         whole=float(np.mean(whole)), fell=fell))
    seg = schedule[1]
    return dict(segments=[dict(start=a, end=b, command=[float(x) for x in c]) for a, b, c in seg],
                rows=rows)


def markdown(res: dict, command: str) -> str:
    head = [f"{s['start']:g}-{s['end']:g} s ({', '.join(f'{x:g}' for x in s['command'])})"
            for s in res["segments"]]
    lines = ["# Tracking error per command segment", "", f"Command: `{command}`", "",
             "Velocity RMSE (m/s) over the steps the closed loop scores (upright, 0.5 s or more "
             "after each change), per stretch of constant command (vx m/s, vy m/s, yaw rate rad/s); "
             "whole: the episode's. Mean over each controller's draws.", "",
             "| controller | draws | " + " | ".join(head) + " | whole |",
             "|---|---:|" + "---:|" * (len(head) + 1)]
    for r in res["rows"]:
        lines.append(f"| {r['label']} | {r['draws']}" + (f" ({r['fell']} fell)" if r["fell"] else "") + " | "
                     + " | ".join("-" if np.isnan(v) else f"{v:.3f}" for v in r["segments"])
                     + f" | {r['whole']:.3f} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("groups", nargs="+", help="LABEL=GLOB of saved traces (trace_*.npz)")
    ap.add_argument("--out", required=True, help="path stem: writes STEM.md and STEM.json")
    a = ap.parse_args(argv)
    groups = {}
    for g in a.groups:
        label, sep, pattern = g.partition("=")
        if not sep or not label or not pattern:
            ap.error(f"{g!r}: expected LABEL=GLOB")
        groups[label] = sorted(glob.glob(pattern))
    res = table(groups)
    command = "python experiments/command_segments.py " + " ".join(f'"{g}"' for g in a.groups) \
        + f" --out {a.out}"
    stem = io.write_table(a.out, dict(command=command, **res), markdown(res, command))
    print(f"wrote {stem}.{{md,json}}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
