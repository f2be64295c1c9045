"""Issue 19, item 3 (session 34): which candidates let the risk-aware STRIDE planner both track
and recover. Velocity RMSE per scenario of the Go1 policy and of four STRIDE planners (seed 0,
one H200): the main table's planner (mean only), and three risk-aware ones (mean + 1 std of 4
residual draws) whose candidates go from the main set to the wide one; the last column is the
1.0 m/s pushes (x 2), where the main planner and the policy fall. A fall is a hatched bar marked
with its time. Reads the rows of ``results/closed_loop_go1_gpu/`` (the main table and
``parts/risk_search/``); writes one PNG.

    python experiments/risk_compose_plot.py --out results/closed_loop_go1_gpu/parts/risk_search/compose.png
"""

from __future__ import annotations

import argparse
import json
import pathlib

from stride_jax.jobs import closed_loop

ROOT = pathlib.Path(__file__).resolve().parents[1] / "results" / "closed_loop_go1_gpu"
SEARCH = ROOT / "parts" / "risk_search"
SCENARIOS = ("slope", "rough", "soft", "changes", "push", "low_friction", "push2x")
# planner label -> (folder of its main-scenario rows, folder of its push x 2 row)
PLANNERS = {
    "policy": (None, "mean_push2x"),
    "STRIDE, main: 64 policy, 256 family, 352 prior 0.08, 352 noise 0.15; mean only": (None, "mean_push2x"),
    "risk-aware, main with noise 0.5 (push not run)": ("hyb_risk_main", "hyb_risk_push2x"),
    "risk-aware, no policy prior: 64 policy, 256 family, 704 noise 0.5": (
        "compose_pol64_fam256_main", "compose_pol64_fam256"),
    "risk-aware, wide: 16 policy, 64 family, 944 noise 0.5": ("wide_risk_std_main",
                                                              "wide_risk_std_push2x"),
}


def _rows(folder: pathlib.Path) -> list[dict]:
    return json.loads((folder / "closed_loop.json").read_text())["rows"]


def table() -> dict[str, dict[str, dict]]:
    """``{planner: {scenario: row}}`` from the stored rows (seed 0)."""
    main = {}
    for r in _rows(ROOT):  # the main table: its seed-0 STRIDE part and the policy's walk part
        if r["scenario"] in SCENARIOS and r.get("part") in ("walk", "seed0_stride_delan_onn_oracle_slope"):
            main.setdefault(r["model"], {})[r["scenario"]] = r
    out = {}
    for label, (scen_dir, push_dir) in PLANNERS.items():
        model = "policy" if label == "policy" else "stride"
        got = dict(main[model]) if scen_dir is None else {
            r["scenario"]: r for r in _rows(SEARCH / scen_dir)}
        got.update({r["scenario"]: r for r in _rows(SEARCH / push_dir) if r["model"] == model})
        out[label] = got
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", required=True)
    a = ap.parse_args(argv)
    closed_loop.bars(table(), list(SCENARIOS), a.out,
                     "Go1, STRIDE-MPPI (K = 1024, H = 20, seed 0, H200): tracking against recovery",
                     labels={"push2x": "pushes x 2\n(1.0 m/s)"}, ylim=0.36)
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
