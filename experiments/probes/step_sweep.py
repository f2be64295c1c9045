"""Runs ``fused_step_check.py`` once per configuration in one process (one start of JAX and one
robot build instead of one per configuration; each configuration still compiles its own kernel):
the whole-step kernel's samples per program, warps per program, unrolled loops, columns per loop
iteration and parts left out, side by side. Each CONFIG is the probe's own flags with ``:`` for
spaces:

    python experiments/probes/step_sweep.py --robot g1 --hidden 64 --samples 1024 -- \
        --kernels:xla,pallas-step-bf16 --rows:8:--warps:16 --rows:4:--warps:8 --rows:8:--skip:solve

The flags before ``--`` go to every configuration; a configuration that fails prints its error
and the sweep goes on.
"""

from __future__ import annotations

import sys
import traceback

import stride_jax


def main(argv: list[str]) -> None:
    if "--" not in argv:
        raise SystemExit(__doc__)
    cut = argv.index("--")
    common, configs = argv[:cut], argv[cut + 1:]
    if not configs:
        raise SystemExit("step_sweep: no configuration after --")
    from experiments.probes import fused_step_check as probe
    from stride_jax.dynamics import fused_step
    knobs = ("ROWS", "WARPS", "UNROLL", "SKIP", "BLOCK", "SPLIT")
    defaults = {k: getattr(fused_step, k) for k in knobs}
    for config in configs:
        flags = [f for f in config.split(":") if f]
        if "--kernels" not in flags:
            flags += ["--kernels", "pallas-step-bf16"]
        print(f"== {' '.join(flags)}", flush=True)
        sys.argv = ["fused_step_check.py", *common, *flags]
        try:
            probe.main()
        except Exception:  # noqa: BLE001 -- a probe: report and go on to the next configuration
            traceback.print_exc(limit=3)
        finally:
            for k, value in defaults.items():
                setattr(fused_step, k, value)


if __name__ == "__main__":
    stride_jax.set_xla_flags()
    main(sys.argv[1:])
