export MENAGERIE_ROOT=/work/shared/menagerie XLA_FLAGS=--xla_cpu_enable_concurrency_optimized_scheduler=false
M=/work/main/results/models/g1_walk_ppo_g1_slope_slope15_tw1_tf0.25
F="--policy results/policies/ppo_g1_soft_ent --learned results/learned_g1_soft/reward_value.msgpack --rough-cm 2 --slope-deg 15 --govern --episodes 1 --planning.model-gravity --planning.trust-limit 2.5 --planning.trust-hold-s 1.0 --planning.family-cost-stop 0.3 --seed 2"
for tree in /tmp/wt415 /work/main; do
  cd $tree && PYTHONPATH=$tree /work/main/.venv/bin/python -m stride_jax.jobs.closed_loop --robot g1 --models stride=$M/stride-s0 --scenarios push,rough --seconds 0.6 --mppi.samples 32 --mppi.horizon 10 --mppi.policy-samples 8 --mppi.family-samples 12 --mppi.prior-fraction 1.0 --prior-noise-std 0.05 --mppi.family-decay 0.8 --planning.observer-gain 0.1 --planning.learned-track-weight 10 $F --controller-repeats 0 --out /tmp/repro_$(basename $tree) > /tmp/repro_$(basename $tree).log 2>&1
done
echo done > /tmp/repro.done
