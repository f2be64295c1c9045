"""Sim-to-real gap diagnosis: logs, effects, replay, diagnosis (where, which, how far) and what
the library of effects leaves. The ``stride gap`` command, its report and the blind benchmark are
jobs: :mod:`stride_jax.jobs.gap`, :mod:`~stride_jax.jobs.gap_report`,
:mod:`~stride_jax.jobs.gap_bench`."""

from stride_jax.gap import finer  # noqa: E402,F401  (registers the finer effects' names in effects.ALL)
