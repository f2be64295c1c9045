"""The wide stage of ``risk_fall_search.py`` as one figure: per seed, the base's lateral velocity
and height through the two 1.0 m/s pushes, the mean-only planner against the risk-aware one (each
line stops where the episode counts a fall). Reads the traces the closed loop wrote in the
search's work folder (``WORK/wide_<kind>_push2x[_seedN]/trace_*.npz``):

    python experiments/risk_fall_plot.py --work /tmp/fs --out results/closed_loop_go1_gpu/parts/risk_search/wide_push2x.png \
        [--seeds 0,1,2,3,4 --cpu-seeds 3,4]
"""

from __future__ import annotations

import argparse
import pathlib

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from risk_fall_search import wide_job  # noqa: E402  (beside this script)
from stride_jax import io  # noqa: E402
from stride_jax.control.scenarios import SCENARIOS  # noqa: E402

KINDS = {"mean": ("mean only", "tab:red"), "risk_std": ("mean + 1 std of 4 residual draws", "tab:blue")}


def trace(work: pathlib.Path, kind: str, seed: int) -> dict | None:
    files = sorted((work / wide_job(kind, seed)).glob("trace_*.npz"))
    if not files:
        return None
    with np.load(files[0]) as z:
        return {k: z[k] for k in z.files}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--work", default="/tmp/fs")
    ap.add_argument("--out", required=True)
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--cpu-seeds", default="", help="seeds whose runs were on the CPU (titled so)")
    a = ap.parse_args(argv)
    seeds = [int(s) for s in a.seeds.split(",")]
    on_cpu = {int(s) for s in a.cpu_seeds.split(",") if s}
    fig, axes = plt.subplots(2, len(seeds), figsize=(3.6 * len(seeds), 5.6), sharex=True, squeeze=False)
    found = 0
    for c, seed in enumerate(seeds):
        for kind, (label, color) in KINDS.items():
            tr = trace(pathlib.Path(a.work), kind, seed)
            if tr is None:
                continue
            found += 1
            up = ~tr["fallen"].astype(bool)
            end = int(np.argmin(up)) if not up.all() else len(up)
            fell = f", fell at {tr['t'][end]:.2f} s" if end < len(up) else ", up"
            axes[0, c].plot(tr["t"][:end], tr["v_base"][:end, 1], color=color, lw=1, label=label + fell)
            axes[1, c].plot(tr["t"][:end], tr["height"][:end], color=color, lw=1)
        for ax in axes[:, c]:
            for t0, dur, *_ in SCENARIOS["push"].pushes:
                ax.axvspan(t0, t0 + dur, color="0.85", lw=0)
        axes[0, c].set_title(f"seed {seed}" + (" (CPU)" if seed in on_cpu else ""))
        axes[0, c].legend(fontsize=7, loc="lower left")
        axes[1, c].set_xlabel("t (s)")
    if not found:
        raise SystemExit(f"no traces under {a.work}/wide_*_push2x*: run the wide stage first")
    axes[0, 0].set_ylabel("lateral velocity vy (m/s)")
    axes[1, 0].set_ylabel("base height (m)")
    fig.suptitle("Go1, STRIDE-MPPI with candidates far from the policy, pushed sideways at 1.0 m/s "
                 "(grey: the pushes)", fontsize=10)
    fig.tight_layout()
    io.atomic_write(a.out, lambda f: fig.savefig(f, format="png", dpi=110))
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
