"""Probe (session 51): at G1's stop in the governed command changes, which candidates the planner
weights and what its model predicts for them. The planner (G1's closed-loop flags at CPU size:
K=256, H=20, 32 policy, 96 family, the rest policy-prior candidates; STRIDE told the gravity, no
observer: it is fed the policy's own states) steps along the policy's episode from 4 s; from 4.9 s
every 0.2 s it prints the weight of each candidate group, the group's mean predicted forward
velocity 0.4 s ahead (the candidates' actions replayed through the model) and its mean cost, and
at the end the family's mean command offset z.

    python experiments/probes/g1_stop_candidates.py results/models/g1_walk_ppo_g1_slope_slope15_tw1_tf0.25/stride-s0 [FAMILY_COST]
        [--policy results/policies/ppo_g1_slope] [--learned results/learned_g1_slope/reward_value.msgpack]
        [--family-cost-stop C]

FAMILY_COST (default 0, G1's closed-loop setting): ``MPPIConfig.family_cost``, the prior that
pulls the family's offsets back to the plain policy; ``--family-cost-stop C``:
``PlanningConfig.family_cost_stop``, the same prior acting at a stop command only (session 58:
``--policy``, ``--learned`` and ``--family-cost-stop`` added; their defaults are session 51's run).
"""
import argparse, time, numpy as np, jax, jax.numpy as jnp
import stride_jax
stride_jax.set_xla_flags()
from stride_jax.sim import model as sim_model
from stride_jax.control import envs, ppo, learned as L, mppi
from stride_jax.control.episode import learned_model, learned_step, policy_alone
from stride_jax.control.planning import PlanningConfig, make_planning, make_planner, mppi_config, split
from stride_jax.control.scenarios import SCENARIOS
ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
ap.add_argument("run")
ap.add_argument("family_cost", nargs="?", type=float, default=0.0)
ap.add_argument("--policy", default="results/policies/ppo_g1_slope")
ap.add_argument("--learned", default="results/learned_g1_slope/reward_value.msgpack")
ap.add_argument("--family-cost-stop", type=float, default=0.0)
args = ap.parse_args()
run, family_cost = args.run, args.family_cost
sm = sim_model.load("g1")
pol = args.policy
ep, env_cfg = policy_alone(sm, SCENARIOS["changes"], pol, govern=True)
policy = ppo.load_policy(pol)[0]  # the planner's candidates
t = np.asarray(ep.t); nq = sm.mj.nq
model, params = learned_model(run, sm)
step = learned_step(model, params)
pcfg = PlanningConfig(observer_gain=0.1, learned_track_weight=10.0, model_gravity=True, prior_noise_std=0.05,
                      family_cost_stop=args.family_cost_stop)
lp = L.load(args.learned, ensemble=True)
planning = make_planning(pcfg, env_cfg, sm, step, policy, lp)
mcfg = mppi.MPPIConfig(samples=256, horizon=20, policy_samples=32, family_samples=96, prior_fraction=1.0, family_decay=0.8, family_cost=family_cost)
mc = mppi_config(mcfg, pcfg, planning)
planner = make_planner(planning, mc)
pstep = jax.jit(planner.step)
K, n_pol, n_fam = mc.samples, mc.policy_samples, mc.family_samples
# mppi's candidate order: plan noise and policy prior, then the policy's, then the family's
groups = {"plan/prior": slice(0, K - n_pol - n_fam), "policy": slice(K - n_pol - n_fam, K - n_fam),
          "family": slice(K - n_fam, K)}
# predicted forward velocity at each rollout step of every candidate (replayed open loop, one key)
def predicted_vx(q_aug, qd, acts, key):
    def body(c, u):
        qa, v = c
        qa2, v2 = planning.dynamics(qa, v, u, key)
        vb, _, _ = envs.base_signals(split(qa2, nq).q, v2, split(qa2, nq).gravity)
        return (qa2, v2), vb[0]
    return jax.lax.scan(body, (q_aug, qd), acts)[1]
pv = jax.jit(jax.vmap(predicted_vx, in_axes=(None, None, 0, None)))
state = planner.init(jax.random.key(0))
i0 = int(np.searchsorted(t, 4.0))
t0 = time.time()
for i in range(i0, len(t)):
    qa = jnp.asarray(ep.q_aug[i]); qd = jnp.asarray(ep.qd[i])
    u, state, info = pstep(state, qa, qd)
    if t[i] >= 4.9 and (i - i0) % 10 == 0:
        w = np.asarray(info.weights); vx = np.asarray(pv(qa, qd, info.candidates, jax.random.key(1)))
        vb, _, _ = envs.base_signals(split(qa, nq).q, qd, split(qa, nq).gravity)
        cmd = np.asarray(split(qa, nq).command)
        line = f"t={t[i]:.2f} cmd {cmd[0]:.1f} real vx {float(vb[0]):+.2f} | plan-weighted predicted vx at 0.2/0.4 s {np.sum(w*vx[:,9]):+.2f}/{np.sum(w*vx[:,-1]):+.2f} |"
        for g, sl in groups.items():
            line += f" {g}: w {w[sl].sum():.2f} vx(0.4s) {vx[sl,-1].mean():+.2f} cost {np.asarray(info.costs)[sl].mean():+.3f} |"
        print(line, flush=True)
print("z mean", state.z, f"({time.time()-t0:.0f} s)")
