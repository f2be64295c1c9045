"""The SHA-256 of every committed checkpoint the report, the closed-loop commands and the MPPI
latency study load, in ``results/SHA256SUMS`` (the format ``sha256sum -c`` reads), so a copy can
be checked with the standard tool and a changed file is noticed (``tests/test_results.py`` checks
the list).

    python experiments/checksums.py            # rewrite results/SHA256SUMS
    cd results && sha256sum -c SHA256SUMS      # check a copy
"""

from __future__ import annotations

import pathlib

ROOT = pathlib.Path(__file__).resolve().parents[1]
RESULTS = ROOT / "results"
# Trained parameters: dynamics models (Table I's seed 0), PPO policies, learned reward/value
# models, and the planning-sized STRIDE runs the MPPI latency study and the fused-kernel checks
# load (``results/mppi_latency/README.md``).
# Glob patterns under ``results/``: every ``learned_*`` folder (the headlines load
# ``learned_go1_slope`` and ``learned_g1_soft``, which the list once left out by naming two).
FOLDERS = ("models", "policies", "learned_*",
           "mppi_latency/planning_sizes/stride-h64", "mppi_latency/planning_sizes/stride-h128",
           "mppi_latency/planning_shared/stride-h64-shared",
           "mppi_latency/planning_shared/stride-h128-shared",
           "dreamer_mpc_go1/value")  # the value and error model fitted on the planner's rollouts


def files(results: pathlib.Path = RESULTS) -> list[pathlib.Path]:
    """Every file under the checkpoint folders, sorted. Hidden files and prose (``*.md``) are
    left out: a README beside a checkpoint is edited by people, and listing it made every edit
    of one fail the check until the list was rewritten (session 92's last CI)."""
    out = []
    for folder in (f for pattern in FOLDERS for f in sorted(results.glob(pattern))):
        out += [p for p in folder.rglob("*")
                if p.is_file() and p.suffix != ".md"
                and not any(part.startswith(".") for part in p.parts)]
    return sorted(out)


def listing(results: pathlib.Path = RESULTS) -> str:
    from stride_jax.io import file_sha256

    return "".join(f"{file_sha256(p)}  {p.relative_to(results).as_posix()}\n"
                   for p in files(results))


def main() -> None:
    from stride_jax.io import atomic_write_text

    atomic_write_text(RESULTS / "SHA256SUMS", listing())
    print(f"wrote {RESULTS / 'SHA256SUMS'} ({len(files())} files)")


if __name__ == "__main__":
    main()
