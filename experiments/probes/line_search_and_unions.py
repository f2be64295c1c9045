"""Two numbers of session 29's gap speed work (results/gap_speed.md, docs/gap.md), measured:

    python experiments/probes/line_search_and_unions.py

1. ``fit.line_search`` on 300 skewed convex losses ``exp(w (v - c)) - w (v - c)`` with known minima
   ``c`` (grid of 7 nodes on [0, 1], as a fit's grid): mean and largest number of evaluations,
   largest error in tolerances, beside SciPy's bounded Brent search in the same cell.
2. ``finer.unions``: the cosine and relative error of a side or end column added up from its limbs'
   against its own replayed column, on Go1 (MJX-training form) explorer logs.

(The "without the confirmation point" figure, 40-400 tolerances, came from a copy of
``line_search`` whose stop did not ask for a nearby point; it is not kept.)
"""

from __future__ import annotations

import numpy as np
from scipy import optimize


def sweep() -> None:
    from stride_jax.gap import fit
    xs = np.linspace(0, 1, 7)
    for tol in (1e-3, 1e-4):
        rng = np.random.default_rng(1)
        ns, err, brent = [], [], []
        for _ in range(300):
            c, w = rng.uniform(0.05, 0.95), rng.uniform(1, 12)
            f = lambda v: np.exp(w * (v - c)) - w * (v - c)
            L = np.array([f(x) for x in xs])
            k = int(np.argmin(L))
            a, b = xs[max(k - 1, 0)], xs[min(k + 1, len(xs) - 1)]
            x, _, n = fit.line_search(f, dict(zip(xs, L)), a, b, tol)
            ns.append(n)
            err.append(abs(x - c) / tol)
            brent.append(optimize.minimize_scalar(f, bounds=(a, b), method="bounded", options={"xatol": tol}).nfev)
        print(f"line_search tol {tol:g}: {np.mean(ns):.2f} evaluations (max {max(ns)}), error at most "
              f"{max(err):.2f} tolerances; bounded Brent {np.mean(brent):.2f}")


def unions() -> None:
    from stride_jax.gap import diagnose, fit, real, screen
    from stride_jax.sim import model
    go1 = model.load("go1")
    _, tr = real.generate(go1, {}, 2, 40, seed=3)
    data = fit.make_data(tr, 2)
    scale = diagnose.scale_of(go1, data)
    rows, cfg = np.arange(len(data.start)), screen.ScreenConfig()
    for b in ("damping", "frictionloss", "armature", "kp_scale", "torque_limit", "servo_damping"):
        for side, parts in (("left", ("FL", "RL")), ("front", ("FR", "FL"))):
            names = [f"{b}@{p}" for p in parts] + [f"{b}@{side}"]
            summed = screen.columns(go1, names, data, scale, cfg, rows, show=False).J_tr[2].ravel()
            own = screen.columns(go1, names[-1:], data, scale, cfg, rows, show=False).J_tr[0].ravel()
            cos = summed @ own / (np.linalg.norm(summed) * np.linalg.norm(own))
            print(f"{b}@{side}: cosine {cos:.4f}, relative error {np.linalg.norm(summed - own) / np.linalg.norm(own):.3f}")


if __name__ == "__main__":
    sweep()
    unions()
