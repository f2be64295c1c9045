"""The alarm stage of ``risk_fall_search.py`` (session 36) as a table and a figure: per planner,
how many of its episodes stayed up through the 1.0 m/s pushes, and per episode how much of the
second before the first push (1-2 s) the planner already spent in its recovery (wide) candidates.
Reads the traces the closed loop wrote (``WORK/<job>/trace_push2x_stride[_seedN].npz``, one
per seed of a job run with ``--episodes``; traces are not tracked in git) and writes the per-
episode numbers (``STEM.json``, tracked) and the figure; ``--from-json`` draws the figure again
from that file alone:

    python experiments/alarm_timing.py --work /tmp/fs --out results/closed_loop_go1_gpu/parts/risk_search/alarm_timing
    python experiments/alarm_timing.py --from-json --out results/closed_loop_go1_gpu/parts/risk_search/alarm_timing
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
from stride_jax.jobs.closed_loop import trace_name  # noqa: E402

# (job folder, label, whether every step plans the recovery candidates by construction)
JOBS = [("main_risk_push2x_seeds", "main set, no alarm", False),
        ("alarm_push2x_seeds", "alarm 0.25 m/s", False),
        ("alarm_hold_push2x", "alarm 0.25 m/s, held 1 s", False),
        ("alarm01_hold_push2x", "alarm 0.1 m/s, held 1 s", False),
        ("alarm_always_push2x", "alarm always ringing", False),
        ("compose_pol64_fam256_push2x_seeds", "always wide (no prior), noise 0.5", True),
        ("compose_pol64_fam256_std0.3_push2x", "always wide (no prior), noise 0.3", True)]
PUSH_S = 2.0  # the first push of the scenario (``scenarios.SCENARIOS['push']``)


def episodes(work: pathlib.Path) -> list[dict]:
    """Per episode of every job found: fell, when, and the share of the second before the push
    spent in the recovery candidates."""
    out = []
    known = {job for job, _, _ in JOBS}
    # the job list lives beside risk_fall_search.py's ALARM (this one adds the figure's labels):
    # say what the two disagree on instead of drawing a partial figure silently
    unknown = sorted(p.parent.name for p in work.glob("*push2x*/closed_loop.json")
                     if p.parent.name not in known)
    if unknown:
        print(f"not drawn (push2x jobs under {work} without a label in JOBS): {', '.join(unknown)}")
    missing = [job for job in known if not (work / job / "closed_loop.json").is_file()]
    if missing:
        print(f"not found under {work}: {', '.join(sorted(missing))}")
    for job, label, wide in JOBS:
        folder = work / job
        if not (folder / "closed_loop.json").is_file():
            continue
        for r in json.loads((folder / "closed_loop.json").read_text())["rows"]:
            tr = np.load(folder / trace_name(r["scenario"], r["model"], r.get("episode", 0),
                                             r.get("seed", 0)))
            before = (tr["t"] > PUSH_S - 1.0) & (tr["t"] <= PUSH_S)
            share = 1.0 if wide else float(tr["alarm"][before].mean())
            after = tr["t"][(tr["t"] > PUSH_S - 0.1) & tr["alarm"].astype(bool)]
            out.append(dict(job=job, label=label, seed=r.get("seed"), fell=bool(r["fell"]),
                            fall_s=r.get("fall_s"), vel_rmse=r["vel_rmse"],
                            wide_share_before_push=share,
                            first_alarm_near_push=float(after[0]) if len(after) and not wide
                            else None))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--work", help="the search's work folder (the jobs' traces)")
    ap.add_argument("--out", required=True, help="path stem: writes STEM.json and STEM.png")
    ap.add_argument("--from-json", action="store_true", help="draw from STEM.json alone")
    a = ap.parse_args(argv)
    stem = pathlib.Path(a.out)
    if a.from_json:
        eps = json.loads(stem.with_suffix(".json").read_text())
    else:
        if not a.work:
            raise SystemExit("--work is needed unless --from-json")
        eps = episodes(pathlib.Path(a.work))
        if not eps:
            raise SystemExit(f"no job of the alarm stage under {a.work}")
        io.atomic_write_text(stem.with_suffix(".json"), json.dumps(eps, indent=1))

    labels = list(dict.fromkeys(e["label"] for e in eps))
    fig, ax = plt.subplots(1, 2, figsize=(13, 4.2), gridspec_kw=dict(width_ratios=[1.1, 1]))
    up = [sum(not e["fell"] for e in eps if e["label"] == lab) for lab in labels]
    n = [sum(e["label"] == lab for e in eps) for lab in labels]
    y = np.arange(len(labels))[::-1]
    ax[0].barh(y, up, color="tab:green", label="stayed up")
    ax[0].barh(y, np.subtract(n, up), left=up, color="tab:red", hatch="//", label="fell")
    ax[0].set_yticks(y, labels, fontsize=8)
    ax[0].set_xlabel("episodes (seeds) through the 1.0 m/s pushes")
    ax[0].legend(fontsize=7, loc="lower right")
    for e in [e for e in eps if "0.3" not in e["label"]]:  # recovery noise 0.5 only
        jitter = 0.02 * (e["seed"] or 0)
        ax[1].scatter(e["wide_share_before_push"] + jitter,
                      (e["fall_s"] - PUSH_S) if e["fell"] else 4.0,
                      color="tab:red" if e["fell"] else "tab:green", s=18,
                      marker="x" if e["fell"] else "o")
    ax[1].set_xlabel("share of the last second before the push in recovery mode", fontsize=9)
    ax[1].set_ylabel("s upright after the push (4: all)", fontsize=9)
    ax[1].set_title("each episode with recovery noise 0.5 (seeds jittered)", fontsize=9)
    fig.suptitle("Go1, risk-aware STRIDE planner, pushes of 1.0 m/s: the recovery is decided "
                 "before the push", fontsize=10)
    fig.tight_layout()
    io.atomic_write(stem.with_suffix(".png"), lambda f: fig.savefig(f, format="png", dpi=120))
    for lab, u, k in zip(labels, up, n):
        print(f"{lab:>40}: {u} of {k} up")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
