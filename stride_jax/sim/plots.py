"""A one-page picture of a dataset (``summary.png`` next to its arrays)."""

from __future__ import annotations

import pathlib

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from stride_jax.sim.dataset import Dataset  # noqa: E402


def dataset_summary(ds: Dataset, path: str | pathlib.Path | None = None) -> pathlib.Path:
    """Coverage, forces and validity of a dataset, in one PNG; returns its path."""
    a, m = ds.arrays, ds.meta
    valid = a["valid"]
    nq_free = 7 if m["floating_base"] else 0
    nv_free = 6 if m["floating_base"] else 0
    dt = m["ctrl_dt"]
    fig, ax = plt.subplots(2, 2, figsize=(11, 8))

    # (a) state coverage of the first actuated joint.
    q = a["q"][..., nq_free][valid]
    qd = a["qd"][..., nv_free][valid]
    if not m["floating_base"]:
        q = np.mod(q + np.pi, 2 * np.pi) - np.pi  # pendulum: angle from the bottom, wrapped
    ax[0, 0].hist2d(q, qd, bins=60, cmap="viridis", cmin=1)
    ax[0, 0].set(title=f"coverage of {m['joints'][0]}", xlabel="q (rad)", ylabel="qd (rad/s)")

    # (b) contact forces of the first valid episode, or the non-conservative torque.
    ep = int(np.argmax(valid.mean(1)))
    t = np.arange(a["q"].shape[1]) * dt
    if m["feet"]:
        for i, foot in enumerate(m["feet"]):
            ax[0, 1].plot(t, a["foot_force"][ep, :, i], lw=0.8, label=foot)
        ax[0, 1].set(title=f"foot normal forces, episode {ep}", xlabel="t (s)", ylabel="N")
        ax[0, 1].legend(fontsize=8)
    else:
        f = (a["qfrc_passive"] + a["qfrc_constraint"] + a["qfrc_external"])[..., 0][valid]
        ax[0, 1].scatter(q, f, s=1, alpha=0.3)
        ax[0, 1].set(title="non-conservative torque: passive + constraint + hidden",
                     xlabel="q (rad)", ylabel="N m", yscale="symlog")

    # (c) fraction of episodes still valid (upright) over time.
    ax[1, 0].plot(t, valid.mean(0))
    ax[1, 0].set(title=f"valid episodes (overall {valid.mean():.0%})", xlabel="t (s)",
                 ylabel="fraction", ylim=(0, 1.05))

    # (d) acceleration magnitudes per dof.
    qdd = np.abs(a["qdd"][valid])
    ax[1, 1].boxplot(qdd[:, : min(qdd.shape[1], 18)], showfliers=False)
    ax[1, 1].set(title="|qdd| per dof (first 18)", xlabel="dof", ylabel="rad/s^2 or m/s^2",
                 yscale="log")
    fig.suptitle(f"{m['robot']}: {m['n_episodes']} episodes x {m['n_steps']} steps "
                 f"({m['backend']}, seed {m['seed']})")
    fig.tight_layout()
    out = pathlib.Path(path or ds.path / "summary.png")
    fig.savefig(out, dpi=90)
    plt.close(fig)
    return out
