"""Jobs: the applications of the library, one module per ``stride`` subcommand, each a frozen
config that nests the library's own configs, its named presets (instances of that config),
and ``run(cfg, command)``.

    data         ``stride data``        simulate a robot, write a dataset folder
    train        ``stride train``       dataset -> trained, checkpointed model
    eval         ``stride eval``        Table I metrics of trained runs
    show         ``stride show``        the pendulum's phase portrait (``make demo``'s figure)
    bench_sim    ``stride bench-sim``   simulation throughput
    bench_mppi   ``stride bench-mppi``  MPPI step latency
    bench_table  the benchmarks' one table writer (JSON + Markdown)
    gap          ``stride gap ...``     the gap tool's subcommands; gap_report (its report),
                 gap_bench (``stride gap bench``, the blind benchmark)
    closed_loop  ``stride closed-loop`` MPPI in closed loop per model and scenario (its config,
                 ``ClosedLoopConfig``, nests ``MPPIConfig`` and ``PlanningConfig``)
    headline     which rows of a merged closed-loop table are the current planner's (no JAX)
    dreamer_mpc  the Dreamer-MPC ablation (``experiments/dreamer_mpc.py``)
    gait_study   the closed-loop gait study (``experiments/closed_loop_gait.py``)
    ppo          ``stride ppo``         one resumable chunk of a PPO policy into a run folder
    fit_reward_value  ``stride fit-reward-value``  learned reward and value from a PPO run
    pool         side-by-side ``stride`` processes for the experiment drivers

The library (``robots``, ``sim``, ``dynamics``, ``train``, ``control``, ``gap``, ``eval``) imports
none of them (``tests/test_layers.py``).
"""
