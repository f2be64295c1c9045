"""Merge a later Table I call's rows into an earlier table of the same robot and dataset.

    python experiments/table1_merge.py results/table1/g1 /tmp/redo/g1 [--out results/table1/g1]

Every model in the second folder's ``table.json`` replaces that model's rows in the first (e.g.
LNN + Diffusion retrained to the shared step count in a call of its own, ``table1.py --models
lnn_diffusion``); both must come from the same evaluation settings and the same dataset (its
sha256), which ``stride_jax.jobs.eval.merge`` checks (``--other-data``: a regenerated dataset
of the same generator and settings, named in the table). Writes ``table.{md,json}`` to ``--out``
(default: the first folder).
"""

from __future__ import annotations

import argparse
import pathlib

from stride_jax.jobs import eval as eval_job


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("base", type=pathlib.Path, help="folder with the earlier table.json")
    p.add_argument("update", type=pathlib.Path, help="folder with the later table.json")
    p.add_argument("--out", type=pathlib.Path, default=None, help="default: base")
    p.add_argument("--other-data", action="store_true",
                   help="allow the later rows' dataset to be a regeneration (other sha256) of the "
                        "same generator and settings; the table names both digests")
    args = p.parse_args(argv)
    eval_job.merge(args.base / "table.json", args.update / "table.json", args.out or args.base,
                   other_data=args.other_data)


if __name__ == "__main__":
    main()
