"""Where the model-trust gate handed a closed loop's robot to the policy, read off a run's rows
and traces (the numbers behind ``results/closed_loop_g1_gpu/README.md``, "Session 86"):

    python experiments/trust_gate.py rows results/closed_loop_g1_gpu/closed_loop.json \\
        --models stride,stride_s1,stride_s2
    python experiments/trust_gate.py traces results/closed_loop_g1_gpu/parts/delay_s0 --limit 2.5
    python experiments/trust_gate.py overspeed results/closed_loop_g1_gpu/parts/h10_stride \\
        --scenario tilt15 --over 0.25

``rows``: per scenario, each row of the named models (the table's ``headline`` parts where it
names them) with its velocity RMSE and the share of its upright steps the gate handed to the
policy (``distrust_share``), and the mean share over them. ``traces``: per saved trace of a
run folder, the control periods the observer's linear estimate lay past ``--limit`` (m/s^2;
with ``--component down``, its downward entry: what a ``--planning.trust-component down`` gate
reads),
the longest run of them without a break (what ``--planning.trust-delay-s`` must outlast for
the gate to plan through it), the most of them in any ``--window-s`` (default 1 s) before the
first handover (what a rule counting crossings per window would read), the periods handed
over, and when the estimate first passed the limit, the gate first handed over and the robot
fell (s). ``overspeed``: per saved trace whose upright forward speed passed the command by
more than ``--over`` (m/s; a robot lurching ahead of its command, say), when it first did, the
most it passed it by, who was acting (the share of the ``--window-s`` before that the gate had
handed to the policy, and from then to the episode's end) and when it fell: the gate's fallback
is the policy, and a runaway under its steps began where the planner handed the robot over.
Prints markdown tables.
"""

from __future__ import annotations

import argparse
import json
import pathlib
from collections.abc import Callable

import numpy as np

from stride_jax.control.mppi import DISTRUSTED
from stride_jax.control.planning import TRUST_READS
from stride_jax.jobs.headline import headline_picks, in_headline


def longest_run(mask: np.ndarray) -> int:
    """The longest run of consecutive True entries of ``mask``."""
    edges = np.flatnonzero(np.diff(np.r_[0, np.asarray(mask, np.int8), 0]))  # starts, ends
    return int((edges[1::2] - edges[::2]).max()) if len(edges) else 0


def _first(mask: np.ndarray, t: np.ndarray) -> float | None:
    """The time of the first True entry of ``mask`` (None: none)."""
    return float(t[np.argmax(mask)]) if mask.any() else None


def _window_periods(window_s: float, t: np.ndarray) -> int:
    """The control periods of a trace (times ``t``, s) in ``window_s`` seconds, at least one."""
    if window_s <= 0:
        raise ValueError(f"window {window_s} s: need a positive length")
    dt = float(t[1] - t[0]) if len(t) > 1 else 1.0
    return max(int(round(window_s / dt)), 1)


def trigger_runs(path: pathlib.Path, limit: float, window_s: float = 1.0,
                 component: str = "norm") -> dict:
    """A trace's periods with the observer's linear estimate (``component``: its norm, as the
    gate reads it by default, or its downward entry) past ``limit``, their longest
    unbroken run, the most of them in any window of ``window_s`` seconds that ends before the
    gate first handed over (the whole trace where it never did), the periods it handed over
    (``status`` DISTRUSTED), and the times (s; None: never) the estimate first passed the
    limit, the gate first handed over and the robot fell."""
    with np.load(path) as z:
        if "disturbance" not in z.files or "status" not in z.files:
            raise ValueError(f"{path}: no disturbance estimate or planner status (a run "
                             "without the observer, or the policy alone)")
        if "t" not in z.files or "fallen" not in z.files:
            raise ValueError(f"{path}: no time or fall flags (not a closed loop's trace)")
        if component not in TRUST_READS:
            raise ValueError(f"component {component!r}: one of {', '.join(TRUST_READS)}")
        over = TRUST_READS[component](np.asarray(z["disturbance"])) > limit
        handed = z["status"] == DISTRUSTED
        t, fallen = np.asarray(z["t"]), np.asarray(z["fallen"], bool)
    width = _window_periods(window_s, t)
    in_window = np.convolve(over.astype(int), np.ones(width, int))[:len(over)]  # ending at each
    before = int(np.argmax(handed)) if handed.any() else len(over)
    return dict(over=int(over.sum()), longest=longest_run(over),
                most_in_window=int(in_window[:before].max()) if before else 0,
                handed=int(handed.sum()), periods=int(len(over)), first_over_s=_first(over, t),
                handed_at_s=_first(handed, t), fell_at_s=_first(fallen, t))


def overspeed(path: pathlib.Path, over: float, window_s: float = 1.0) -> dict | None:
    """A trace's forward overspeed while upright: None where its forward speed never passed
    the command by more than ``over`` (m/s); else the time it first did (s), the most it did
    (m/s), the share of the ``window_s`` seconds before that time and of the periods from it to
    the end that the gate handed to the policy, and when the robot fell (s; None: never)."""
    with np.load(path) as z:
        missing = {"t", "v_base", "command", "status", "fallen"} - set(z.files)
        if missing:
            raise ValueError(f"{path}: no {', '.join(sorted(missing))} (not a planner's "
                             "closed-loop trace)")
        t, fallen = np.asarray(z["t"]), np.asarray(z["fallen"], bool)
        excess = np.asarray(z["v_base"])[:, 0] - np.asarray(z["command"])[:, 0]
        handed = z["status"] == DISTRUSTED
    width = _window_periods(window_s, t)
    fast = (excess > over) & ~fallen
    if not fast.any():
        return None
    i = int(np.argmax(fast))
    lo = max(i - width, 0)
    return dict(first_s=float(t[i]), most=float(excess[~fallen].max()),
                handed_before=float(handed[lo:i].mean()) if i > lo else None,
                handed_after=float(handed[i:].mean()), fell_at_s=_first(fallen, t))


def row_shares(table: dict, models: list[str]) -> dict[str, dict]:
    """Per scenario, ``(model, seed, vel_rmse, fell, distrust_share)`` of the rows of
    ``models`` (names before any ``@part``; the headline's rows where the table has one) and
    their mean share."""
    picks = headline_picks(table)
    out: dict[str, dict] = {}
    for r in table["rows"]:
        if r["model"].split("@")[0] not in models or (picks and not in_headline(r, picks)):
            continue
        if r.get("distrust_share") is None:
            continue
        out.setdefault(r["scenario"], {"rows": []})["rows"].append(
            (r["model"], r.get("seed", 0), r["vel_rmse"], bool(r["fell"]), r["distrust_share"]))
    for cell in out.values():
        cell["mean_share"] = float(np.mean([x[-1] for x in cell["rows"]]))
    return out


def _each_trace(files: list[pathlib.Path], read: Callable, cells: int):
    """``(file, read(file))`` per trace ``read`` could read; for one it could not (a
    ``ValueError``), a table row with the reason and ``cells`` columns after the name."""
    for f in files:
        try:
            got = read(f)
        except ValueError as e:
            print(f"| {f.parent.name}/{f.name} | {e} |" + " |" * (cells - 1))
            continue
        yield f, got


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="what", required=True)
    r = sub.add_parser("rows", help="rows' handed-over shares per scenario")
    r.add_argument("table", help="a closed_loop.json")
    r.add_argument("--models", required=True, help="comma-separated model names")
    t = sub.add_parser("traces", help="trigger runs per saved trace")
    t.add_argument("folders", nargs="+", help="closed-loop run folders (their trace_*.npz)")
    t.add_argument("--limit", type=float, required=True, help="the gate's limit (m/s^2)")
    t.add_argument("--window-s", type=float, default=1.0,
                   help="the window of the most periods past the limit before a handover (s)")
    t.add_argument("--scenario", default="", help="only this scenario's traces")
    t.add_argument("--component", choices=sorted(TRUST_READS), default="norm",
                   help="what of the estimate the gate read (--planning.trust-component)")
    o = sub.add_parser("overspeed", help="who acted when the robot ran past its command")
    o.add_argument("folders", nargs="+", help="closed-loop run folders (their trace_*.npz)")
    o.add_argument("--over", type=float, required=True,
                   help="forward speed above the command that counts (m/s)")
    o.add_argument("--scenario", default="", help="only this scenario's traces")
    o.add_argument("--window-s", type=float, default=1.0,
                   help="the window before the overspeed whose handed-over share is read (s)")
    a = ap.parse_args(argv)
    if a.what == "rows":
        path = pathlib.Path(a.table)
        if not path.is_file():
            raise SystemExit(f"{path}: no such table")
        got = row_shares(json.loads(path.read_text()), a.models.split(","))
        if not got:
            raise SystemExit(f"{path}: no row of {a.models} with a distrust_share")
        print("| scenario | rows: model (planner seed) vel RMSE, handed over | mean handed over |")
        print("|---|---|---:|")
        for sc, cell in got.items():
            rows = "; ".join(f"{m} ({s}) {v:.3f}{' fell' if f else ''}, {d:.0%}"
                             for m, s, v, f, d in cell["rows"])
            print(f"| {sc} | {rows} | {cell['mean_share']:.0%} |")
        return 0
    pattern = f"trace_{a.scenario}_*.npz" if a.scenario else "trace_*.npz"
    files = [f for d in a.folders for f in sorted(pathlib.Path(d).glob(pattern))]
    if not files:
        raise SystemExit(f"{a.folders}: no {pattern} (traces stay where the closed loop ran)")
    if a.window_s <= 0:
        raise SystemExit(f"--window-s {a.window_s}: need a positive length")
    secs = lambda x: "-" if x is None else f"{x:.2f}"  # noqa: E731
    if a.what == "overspeed":
        print(f"| trace | first {a.over:g} m/s over the command (s) | most over (m/s) | handed "
              f"over in the {a.window_s:g} s before | handed over from then | fell at (s) |")
        print("|---|---:|---:|---:|---:|---:|")
        share = lambda x: "-" if x is None else f"{x:.0%}"  # noqa: E731
        calm = []
        for f, g in _each_trace(files, lambda f: overspeed(f, a.over, a.window_s), 5):
            if g is None:
                calm.append(f)
                continue
            print(f"| {f.parent.name}/{f.name} | {g['first_s']:.2f} | {g['most']:.2f} | "
                  f"{share(g['handed_before'])} | {share(g['handed_after'])} | "
                  f"{secs(g['fell_at_s'])} |")
        print(f"\n{len(files) - len(calm)} of {len(files)} traces ran more than {a.over:g} m/s "
              "past their command while upright")
        return 0
    print(f"| trace | periods past {a.limit:g} m/s^2 | longest run | most in {a.window_s:g} s "
          "before a handover | handed over | periods | first past (s) | first handed over (s) "
          "| fell at (s) |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for f, g in _each_trace(files, lambda f: trigger_runs(f, a.limit, a.window_s, a.component),
                            8):
        print(f"| {f.parent.name}/{f.name} | {g['over']} | {g['longest']} | "
              f"{g['most_in_window']} | {g['handed']} | {g['periods']} | "
              f"{secs(g['first_over_s'])} | {secs(g['handed_at_s'])} | {secs(g['fell_at_s'])} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
