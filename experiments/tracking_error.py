"""Where a planner's velocity tracking error comes from: the closed loop's saved traces split
into a steady offset (forward and lateral mean of velocity minus command) and what varies about
it (the gait's sway, oscillation), over the steps the RMSE is scored on (upright, the run's
settle time or more after a command change: ``stride_jax.control.episode.tracked``).

    python experiments/tracking_error.py --scenario changes \\
        "STRIDE=results/closed_loop_go1_gpu/parts/full_changes:stride" \\
        "DeLaN + MLP=results/closed_loop_go1_gpu/parts/full_changes:delan" \\
        "ONN=results/closed_loop_go1_gpu/parts/eq_changes:onn" \\
        --out results/planning_diagnosis/changes_error_go1
    python experiments/tracking_error.py --scenario tilt --window-s 1 "STRIDE=DIR:stride" ... --out OUT

(``--window-s``: also the forward offset and the RMSE per window of the episode, and the share
of its steps the model-trust gate handed to the policy.)

A ``LABEL=FOLDER:MODEL`` picks, from a closed-loop run's folder (``closed_loop.json`` and its
traces), the rows of that model kind in the scenario: every trained seed (``MODEL``,
``MODEL_sN``) and planner draw. The mean square error of the pooled steps is
the squared offset plus the variance about it, per axis; each trained seed's forward offset is
listed so that a difference between kinds can be read against the spread of their seeds. Writes
``OUT.md``, ``OUT.json`` and ``OUT.png``; where the scenario's command changes, a second table splits
each model's error over the stretches of constant command (the mean over its traces of each
one's RMSE there). Where the traces record the planner's status (runs since the trust gate,
session 41), a third table splits the pooled error over the steps the model-trust gate handed
to the policy (``mppi.DISTRUSTED``) and those the plan acted on: whether a planner loses where
it plans or where it hands over (a push that trips the gate, a model it stops trusting). Needs
the traces (``trace_*.npz``), which stay out of the repository: run it where the closed loop
ran.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import shlex
import sys
import types

import numpy as np

from stride_jax.control.episode import tracked
from stride_jax.control.mppi import DISTRUSTED
from stride_jax.io import atomic_write, write_table
from stride_jax.jobs import closed_loop
from stride_paper.seeds import kind_and_seed


def traces(folder: pathlib.Path, scenario: str, model: str) -> dict[int, list[pathlib.Path]]:
    """The trace files of ``model``'s rows in ``scenario`` (the folder's ``closed_loop.json``)
    per trained seed, every planner draw of each: a row's kind and seed as the report reads
    them (``stride_paper.seeds.kind_and_seed``), its file as the closed loop names it."""
    table = folder / "closed_loop.json"
    if not table.is_file():
        raise FileNotFoundError(f"{folder}: no closed_loop.json (a closed-loop run's folder)")
    out: dict[int, list[pathlib.Path]] = {}
    for r in json.loads(table.read_text())["rows"]:
        kind, seed = kind_and_seed(r)
        if r["scenario"] != scenario or kind != model:
            continue
        path = folder / closed_loop.trace_name(r["scenario"], r["model"], r.get("episode", 0),
                                   r.get("seed", 0))
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no trace of the row {r['model']} (the traces "
                                    "stay where the closed loop ran)")
        out.setdefault(seed, []).append(path)
    return out


def load(path: pathlib.Path, planner: bool = True) -> types.SimpleNamespace:
    """A trace's arrays (``name``: its file's); ``status`` (the planner's, per step) None where
    it has none: older runs, or ``planner`` False (the policy alone records zeros, which say
    nothing of a gate). The functions below take traces so loaded, each file read once."""
    with np.load(path) as z:
        tr = types.SimpleNamespace(**{k: z[k] for k in ("t", "command", "fallen", "v_base")})
        tr.status = z["status"] if planner and "status" in z.files else None
    tr.name = pathlib.Path(path).name
    return tr


def handed_over(tr) -> np.ndarray:
    """Per step, whether the model-trust gate handed the robot to the policy (all False where
    the trace records no planner status: nothing was handed over)."""
    if tr.status is None:
        return np.zeros(len(tr.t), bool)
    return np.asarray(tr.status) == DISTRUSTED


def by_gate(loaded: list[types.SimpleNamespace], settle_s: float) -> dict | None:
    """The pooled scored steps split by who acted: the share the trust gate handed to the
    policy, and the velocity RMSE over those and over the planned ones (NaN: none); None where
    no trace records a planner status (loaded with ``planner`` False: the policy alone)."""
    if all(tr.status is None for tr in loaded):
        return None
    e2, gate = [], []
    for tr in loaded:
        use = tracked(tr, settle_s)
        e2.append(np.sum((tr.v_base[:, :2] - tr.command[:, :2]) ** 2, axis=1)[use])
        gate.append(handed_over(tr)[use])
    e2, gate = np.concatenate(e2), np.concatenate(gate)
    rmse = lambda m: float(np.sqrt(e2[m].mean())) if m.any() else float("nan")  # noqa: E731
    return dict(share=float(gate.mean()) if len(gate) else float("nan"),
                rmse_handed_over=rmse(gate), rmse_planned=rmse(~gate))


def errors(tr: types.SimpleNamespace, settle_s: float) -> np.ndarray:
    """Velocity minus command (x, y in the base frame) on a trace's scored steps."""
    return (tr.v_base[:, :2] - tr.command[:, :2])[tracked(tr, settle_s)]


def schedule(tr) -> list[tuple[float, float, list[float]]]:
    """``(start s, end s, command [3])`` of each stretch of constant command of a trace."""
    t, c = np.asarray(tr.t), np.asarray(tr.command)
    starts = np.flatnonzero(np.r_[True, np.any(np.diff(c, axis=0) != 0, axis=1)])
    ends = np.r_[starts[1:], len(t)]
    dt = float(t[1] - t[0]) if len(t) > 1 else 0.0
    return [(float(t[a]), float(t[b - 1]) + dt, [float(x) for x in c[a]]) for a, b in zip(starts, ends)]


def segment_rmse(tr: types.SimpleNamespace,
                 settle_s: float) -> tuple[list, list[float], float, bool]:
    """A trace's schedule, its velocity RMSE over the scored steps of each stretch of constant
    command (NaN: none scored) and over all of them (the closed loop's ``vel_rmse``), and
    whether it fell."""
    use, t = tracked(tr, settle_s), np.asarray(tr.t)
    e2 = np.sum((tr.v_base[:, :2] - tr.command[:, :2]) ** 2, axis=1)
    rmse = lambda m: float(np.sqrt(e2[m].mean())) if m.any() else float("nan")
    sched = schedule(tr)
    return sched, [rmse(use & (t >= a) & (t < b)) for a, b, _ in sched], rmse(use), bool(tr.fallen.any())


def by_segment(loaded: list[types.SimpleNamespace], settle_s: float) -> dict:
    """Per stretch of constant command, the mean over the traces (planner draws) of each one's
    RMSE there (:func:`segment_rmse`; NaN where no trace scored a step); the traces must share
    one schedule."""
    key = lambda sched: [(round(a, 6), [round(x, 6) for x in c]) for a, _, c in sched]
    got = [segment_rmse(tr, settle_s) for tr in loaded]
    sched = got[0][0]
    for tr, g in zip(loaded, got):
        if key(g[0]) != key(sched):
            raise ValueError(f"{tr.name}: its command schedule differs from {loaded[0].name}'s")
    per = np.array([g[1] for g in got])
    mean = [float(np.mean(col[np.isfinite(col)])) if np.isfinite(col).any() else float("nan")
            for col in per.T]
    return dict(schedule=[dict(start=a, end=b, command=c) for a, b, c in sched], rmse=mean,
                whole=float(np.mean([g[2] for g in got])), fell=sum(g[3] for g in got))


def by_window(loaded: list[types.SimpleNamespace], settle_s: float, window_s: float) -> dict:
    """Per window of ``window_s`` seconds from the episode's start, the forward offset and the
    velocity RMSE over each trace's scored steps there, means over the traces (NaN: no trace
    scored a step): where in the episode an error arises (a transient after a slope's onset, a
    steady offset); and the share of those steps the trust gate handed to the policy (NaN
    without a planner status, or loaded with ``planner`` False: the policy alone)."""
    if window_s <= 0:
        raise ValueError(f"window {window_s} s: need a positive length")
    offset, rmse, handed = [], [], []
    for tr in loaded:
        use, t = tracked(tr, settle_s), np.asarray(tr.t)
        e = tr.v_base[:, :2] - tr.command[:, :2]
        gate = handed_over(tr)
        # a step's time ends its period: window k holds (k w, (k + 1) w], the first also t = 0
        k_of = np.maximum(np.ceil(t / window_s - 1e-9).astype(int) - 1, 0)
        w = [use & (k_of == k) for k in range(int(k_of.max()) + 1 if len(t) else 0)]
        offset.append([float(e[m, 0].mean()) if m.any() else np.nan for m in w])
        rmse.append([float(np.sqrt((e[m] ** 2).sum(1).mean())) if m.any() else np.nan for m in w])
        handed.append([float(gate[m].mean()) if m.any() and tr.status is not None else np.nan
                       for m in w])
    width = max(len(r) for r in rmse)
    pad = lambda rows: np.array([r + [np.nan] * (width - len(r)) for r in rows])  # noqa: E731
    mean = lambda a: [float(np.nanmean(c)) if np.isfinite(c).any() else float("nan") for c in a.T]  # noqa: E731
    return dict(window_s=window_s, start=[k * window_s for k in range(width)],
                offset_x=mean(pad(offset)), rmse=mean(pad(rmse)), handed_over=mean(pad(handed)))


def split(e: np.ndarray) -> dict:
    """Offset and variance per axis of pooled errors ``[n, 2]``; ``mse`` is their sum."""
    if len(e) == 0:
        raise ValueError("no scored steps (every step fell or followed a command change)")
    bias, var = e.mean(0), e.var(0)
    mse = float(np.mean(np.sum(e ** 2, axis=1)))
    return dict(steps=int(len(e)), offset_x=float(bias[0]), offset_y=float(bias[1]),
                var_x=float(var[0]), var_y=float(var[1]), mse=mse, rmse=float(np.sqrt(mse)))


def run_settle_s(folder: pathlib.Path) -> float:
    """The settle time the run scored its rows with (its config in ``closed_loop.json``)."""
    env = json.loads((folder / "closed_loop.json").read_text()).get("env", {})
    default = closed_loop.ClosedLoopConfig.settle_s  # a run that recorded none ran the default
    return float((env.get("config") or {}).get("settle_s", default))


def decompose(folder: pathlib.Path, scenario: str, model: str,
              settle_s: float | None = None, window_s: float = 0.0) -> dict:
    """The pooled split of ``model``'s traces in ``scenario`` (:func:`split`), its episodes,
    trained seeds and each seed's forward offset; ``settle_s``: the run's own unless given;
    ``window_s`` > 0: also :func:`by_window` (``windows``)."""
    seeds = traces(folder, scenario, model)
    settle_s = run_settle_s(folder) if settle_s is None else settle_s
    if not seeds:
        raise FileNotFoundError(f"{folder}: no row of {model} in {scenario!r}")
    planner = model != "policy"
    loaded = {s: [load(f, planner) for f in fs] for s, fs in seeds.items()}
    per = {s: np.concatenate([errors(tr, settle_s) for tr in trs]) for s, trs in loaded.items()}
    every = [tr for s in sorted(loaded) for tr in loaded[s]]
    return dict(split(np.concatenate(list(per.values()))), settle_s=settle_s,
                episodes=sum(len(fs) for fs in seeds.values()), seeds=sorted(seeds),
                seed_offset_x=[float(per[s][:, 0].mean()) for s in sorted(per)],
                segments=by_segment(every, settle_s),
                gate=by_gate(every, settle_s),
                **({"windows": by_window(every, settle_s, window_s)}
                   if window_s > 0 else {}))


def figure(rows: dict[str, dict], out: pathlib.Path, title: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    labels = list(rows)
    parts = [("forward offset^2", lambda r: r["offset_x"] ** 2),
             ("lateral offset^2", lambda r: r["offset_y"] ** 2),
             ("forward variance", lambda r: r["var_x"]), ("lateral variance", lambda r: r["var_y"])]
    fig, ax = plt.subplots(figsize=(max(5.0, 1.4 * len(labels) + 2), 3.6))
    bottom = np.zeros(len(labels))
    for name, get in parts:
        h = np.array([get(rows[k]) for k in labels])
        ax.bar(labels, h, bottom=bottom, label=name)
        bottom += h
    ax.set_ylabel("mean square velocity error (m/s)^2")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    atomic_write(out, lambda f: fig.savefig(f, format="png", dpi=130))
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("picks", nargs="+", help="LABEL=FOLDER:MODEL")
    ap.add_argument("--scenario", required=True)
    ap.add_argument("--settle-s", type=float, default=None,
                    help="score from this long after a command change (default: each run's own)")
    ap.add_argument("--window-s", type=float, default=0.0,
                    help="also split the error over windows of this many seconds (0: not)")
    ap.add_argument("--out", required=True, help="path stem: writes STEM.md, .json, .png")
    ap.add_argument("--title", default="")
    a = ap.parse_args(argv)
    rows = {}
    for pick in a.picks:
        label, eq, rest = pick.partition("=")
        folder, colon, model = rest.rpartition(":")
        if not (eq and colon and label and folder and model):
            raise SystemExit(f"{pick!r}: expected LABEL=FOLDER:MODEL")
        if not pathlib.Path(folder).is_dir():
            raise SystemExit(f"{pick!r}: no folder {folder}")
        try:
            rows[label] = dict(decompose(pathlib.Path(folder), a.scenario, model, a.settle_s, a.window_s),
                               source=f"{folder}:{model}")
        except (FileNotFoundError, ValueError) as e:
            raise SystemExit(f"{pick!r}: {e}") from None
    title = a.title or f"Velocity tracking error in '{a.scenario}': offset and variance"
    settle = sorted({r["settle_s"] for r in rows.values()})
    md = [f"# {title}", "",
          "Scored steps pooled over every trace of a model (upright, "
          f"{' / '.join(f'{x:g}' for x in settle)} s or more after a command change, as the "
          "runs scored them); MSE = offset_x^2 + offset_y^2 + var_x + var_y (m/s, "
          "(m/s)^2); x forward, y lateral in the base frame. Per seed: each trained seed's "
          "forward offset.", "",
          "| model | episodes | steps | RMSE (pooled) | forward offset | lateral offset | "
          "forward var | lateral var | offsets' share of MSE | forward offset per seed |",
          "|---|---:|---:|---:|---:|---:|---:|---:|---:|---|"]
    for label, r in rows.items():
        share = (r["offset_x"] ** 2 + r["offset_y"] ** 2) / r["mse"]
        md.append(f"| {label} | {r['episodes']} | {r['steps']} | {r['rmse']:.4f} | "
                  f"{r['offset_x']:+.4f} | {r['offset_y']:+.4f} | {r['var_x']:.2e} | "
                  f"{r['var_y']:.2e} | {share:.0%} | "
                  + " / ".join(f"{v:+.4f}" for v in r["seed_offset_x"]) + " |")
    scheds = [r["segments"]["schedule"] for r in rows.values()]
    if len(scheds[0]) > 1 and all(s == scheds[0] for s in scheds):
        head = [f"{s['start']:g}-{s['end']:g} s ({', '.join(f'{x:g}' for x in s['command'])})"
                for s in scheds[0]]
        md += ["", "Per stretch of constant command (vx m/s, vy m/s, yaw rate rad/s): velocity "
               "RMSE over its scored steps, mean over the model's traces (planner draws); whole: "
               "the mean of the traces' own RMSE (the closed loop's `vel_rmse`).", "",
               "| model | episodes | " + " | ".join(head) + " | whole |",
               "|---|---:|" + "---:|" * (len(head) + 1)]
        for label, r in rows.items():
            g = r["segments"]
            md.append(f"| {label} | {r['episodes']}" + (f" ({g['fell']} fell)" if g["fell"] else "")
                      + " | " + " | ".join("-" if np.isnan(v) else f"{v:.3f}" for v in g["rmse"])
                      + f" | {g['whole']:.3f} |")
    if any(r["gate"] for r in rows.values()):
        md += ["", "Who acted, over the pooled scored steps: the share the model-trust gate handed "
               "to the policy (`mppi.DISTRUSTED`), and the velocity RMSE (m/s) over those steps "
               "and over the steps the plan acted on (-: none, or no planner status recorded: "
               "the policy alone acts on all of its own steps).", "",
               "| model | handed to the policy | RMSE there | RMSE where planned |",
               "|---|---:|---:|---:|"]
        fmt = lambda v: "-" if np.isnan(v) else f"{v:.3f}"  # noqa: E731
        for label, r in rows.items():
            g = r["gate"]
            md.append(f"| {label} | - | - | - |" if g is None else
                      f"| {label} | {g['share']:.0%} | {fmt(g['rmse_handed_over'])} | "
                      f"{fmt(g['rmse_planned'])} |")
    if a.window_s > 0:
        starts = max((r["windows"]["start"] for r in rows.values()), key=len)
        head = [f"{x:g}-{x + a.window_s:g} s" for x in starts]
        md += ["", f"Per {a.window_s:g} s of the episode: forward offset and velocity RMSE (m/s) over "
               "the scored steps there, means over the model's traces; where the traces record "
               "the planner's status, the share of those steps the trust gate handed to the "
               "policy.", "",
               "| model | | " + " | ".join(head) + " |", "|---|---|" + "---:|" * len(head)]
        for label, r in rows.items():
            for what, key, form in (("forward offset", "offset_x", "+.3f"), ("RMSE", "rmse", ".3f"),
                                    ("handed to the policy", "handed_over", ".0%")):
                if key == "handed_over" and r["gate"] is None:
                    continue
                vals = r["windows"][key] + [float("nan")] * (len(head) - len(r["windows"][key]))
                md.append(f"| {label} | {what} | "
                          + " | ".join("-" if np.isnan(v) else format(v, form) for v in vals) + " |")
    command = "python experiments/tracking_error.py " + " ".join(
        shlex.quote(x) for x in (sys.argv[1:] if argv is None else argv))
    stem = write_table(a.out, dict(title=title, command=command, scenario=a.scenario, rows=rows),
                       "\n".join(md) + "\n")
    figure(rows, stem.with_suffix(".png"), title)
    print(f"wrote {stem}.{{md,json,png}}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
