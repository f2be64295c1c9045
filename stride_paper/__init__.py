"""The paper's reproduction beside the library: Table I and figure drivers, the report.

Applications of :mod:`stride_jax`, which imports nothing from here:

* :mod:`stride_paper.figures`: the paper's figures on our data (``experiments/reproduce.py``):
  the config and driver, one module per figure family (``figures_pendulum``,
  ``figures_rollout``, ``figures_forces``), the runs they read (``figure_runs``) and what they
  share (``figure_context``);
* :mod:`stride_paper.claims`: the paper's claims and numbers beside ours;
* :mod:`stride_paper.layout`: where the reproduction finds (or makes) its datasets and runs;
* :mod:`stride_paper.report` (with ``report_common``, ``report_control``, ``report_table1``):
  ``results/REPORT.md`` from the result files (``experiments/report.py``).

The metrics these call (rollout error, forces, distributions, contact, horizon, phase portrait,
residual allocation, NFE trade-off) are the library's, in :mod:`stride_jax.eval`.
"""
