"""PPO chunks: a tiny run learns a toy tracking task, and resuming from disk continues exactly as
the in-memory run does. The toy environment (one velocity that follows the action, a command to
track) keeps compilation to seconds; the Go1 environment is checked in test_control_envs."""

import dataclasses
import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from brax.envs import base as brax_base

from stride_jax.control import ppo


class Track(brax_base.Env):
    """v' = 0.5 v + 0.5 a with a in [-1, 1]; reward exp(-(v' - c)^2 / 0.1); obs (v, c)."""

    def reset(self, rng):
        c = jax.random.uniform(rng, minval=-0.8, maxval=0.8)
        return brax_base.State(jnp.zeros(()), jnp.stack([0.0, c]), jnp.zeros(()), jnp.zeros(()),
                               {"err": jnp.zeros(())}, {"c": c})

    def step(self, state, action):
        c = state.info["c"]
        v = 0.5 * state.pipeline_state + 0.5 * action[0]
        err = (v - c) ** 2
        return state.replace(pipeline_state=v, obs=jnp.stack([v, c]), reward=jnp.exp(-err / 0.1),
                             metrics={"err": err})

    observation_size = property(lambda self: 2)
    action_size = property(lambda self: 1)
    backend = property(lambda self: "toy")


CFG = ppo.PPOConfig(num_envs=16, episode_length=10, unroll_length=10, batch_size=16,
                    num_minibatches=4, num_updates_per_batch=2, chunk_steps=8 * 640, checkpoints=2,
                    total_steps=10 ** 6, learning_rate=3e-3, entropy_cost=1e-3, policy_width=16,
                    policy_depth=2, value_width=16, value_depth=2, discounting=0.9)


def _tracking_error(cfg, state, n=64):
    policy, _ = ppo.make_policy(cfg, state.train.params, 2, 1, deterministic=True)
    c = jnp.linspace(-0.8, 0.8, n)
    obs = jnp.stack([jnp.zeros(n), c], axis=-1)
    a = jax.vmap(policy)(obs, jax.random.split(jax.random.key(0), n))[:, 0]
    return float(jnp.mean((0.5 * a - c) ** 2))  # error of the first step from rest


def test_tiny_chunks_learn_and_resume_exactly(tmp_path):
    env = Track()
    trainer = ppo.make_trainer(CFG, env)
    fresh = ppo.RunState(trainer.init(jax.random.key(CFG.seed)), 0, 0)
    first = ppo.train_chunk(CFG, env, trainer=trainer)
    assert first.env_steps == CFG.chunk_steps and first.chunks == 1
    ppo.save(tmp_path, first)
    loaded = ppo.load(tmp_path, CFG, 2, 1)
    assert (loaded.env_steps, loaded.chunks) == (first.env_steps, first.chunks)
    for a, b in zip(jax.tree.leaves(loaded.train), jax.tree.leaves(first.train)):
        np.testing.assert_array_equal(a, b)
    continued = ppo.train_chunk(CFG, env, first, trainer=trainer)
    resumed = ppo.train_chunk(CFG, env, loaded, trainer=trainer)
    assert resumed.env_steps == 2 * CFG.chunk_steps and resumed.chunks == 2
    for a, b in zip(jax.tree.leaves(resumed.train), jax.tree.leaves(continued.train)):
        np.testing.assert_array_equal(a, b)
    changed = [not np.array_equal(a, b) for a, b in
               zip(jax.tree.leaves(first.train.policy), jax.tree.leaves(continued.train.policy))]
    assert any(changed)
    # It learned: the deterministic policy tracks far better than at initialisation.
    assert _tracking_error(CFG, continued) < 0.3 * _tracking_error(CFG, fresh)


def test_a_complete_run_does_nothing_and_configs_are_checked():
    done = dataclasses.replace(CFG, total_steps=640 * 4)
    state = ppo.RunState(ppo.init_state(done, 2, 1, jax.random.key(0)), done.total_steps, 3)
    assert ppo.train_chunk(done, Track(), state) is state
    with pytest.raises(ValueError, match="multiple of num_envs"):
        ppo.PPOConfig(num_envs=10, batch_size=16, num_minibatches=1)
    with pytest.raises(ValueError, match="chunk_steps"):
        ppo.PPOConfig(chunk_steps=10)
    with pytest.raises(ValueError, match="unknown PPO preset"):
        ppo.preset("huge")


def test_loading_into_other_networks_is_refused(tmp_path):
    state = ppo.RunState(ppo.init_state(CFG, 2, 1, jax.random.key(0)), 0, 1)
    ppo.save(tmp_path, state)
    wider = dataclasses.replace(CFG, policy_width=32)
    with pytest.raises(ValueError, match="networks|shapes"):
        ppo.load(tmp_path, wider, 2, 1)


@pytest.mark.slow  # PPO's chunks and resume: test_tiny_chunks_learn_and_resume_exactly
def test_the_ppo_and_fit_reward_value_jobs_at_tiny_size(tmp_path, capsys):
    """`stride ppo` writes a run folder (config, checkpoint, progress) and refuses another
    network on it; `stride fit-reward-value` fits the learned models from that run."""
    from stride_jax import cli
    from stride_jax.control import envs, learned

    run = tmp_path / "ppo"
    cli.main(["ppo", "--robot", "go1", "--preset", "tiny", "--out", str(run)])
    assert {"config.json", "checkpoint.msgpack", "progress.jsonl"} <= {
        p.name for p in run.iterdir()}
    policy, _, env_cfg = ppo.load_policy(run)
    assert env_cfg.robot == "go1"
    with pytest.raises(SystemExit, match="another robot, network or environment"):
        cli.main(["ppo", "--preset", "tiny", "--policy-width", "32", "--out", str(run)])
    # the domain randomisation flags reach the environment: another friction is another run
    with pytest.raises(SystemExit, match="another robot, network or environment"):
        cli.main(["ppo", "--preset", "tiny", "--friction-min", "0.5", "--out", str(run)])
    # a run started before those fields existed resumes (they read back at their defaults)
    import json

    from stride_jax.jobs import ppo as ppo_job
    path = run / "config.json"
    old = json.loads(path.read_text())
    for key in ("friction_min", "friction_max", "action_noise"):
        del old["env"][key], old["ppo"][key]
    path.write_text(json.dumps(old))
    cfg, env_cfg = ppo.read_config(run)
    assert (env_cfg.friction_min, env_cfg.action_noise) == (1.0, 0.0)
    ppo_job._write_config(run, cfg, env_cfg)
    with pytest.raises(ValueError, match="environment"):
        ppo_job._write_config(run, cfg, dataclasses.replace(env_cfg, action_noise=0.02))
    # --init-from: a new run (here under action noise) starts from that run's networks, at 0 steps
    started = []

    def first_chunk(cfg, env, restore, *args, **kw):
        started.append(restore)
        return restore

    env = envs.VelocityEnv(env_cfg)
    trained = ppo.load(run, cfg, env.observation_size, env.action_size)
    with pytest.MonkeyPatch.context() as monkey:
        monkey.setattr(ppo_job, "train_chunk", first_chunk)
        cli.main(["ppo", "--preset", "tiny", "--init-from", str(run), "--action-noise", "0.02",
                  "--out", str(tmp_path / "robust")])
        with pytest.raises(SystemExit, match="no checkpoint.msgpack"):
            cli.main(["ppo", "--preset", "tiny", "--init-from", str(tmp_path),
                      "--out", str(tmp_path / "other")])
    assert (started[0].env_steps, started[0].chunks) == (0, 0)
    same = jax.tree.map(lambda a, b: bool(jnp.array_equal(a, b)), started[0].train, trained.train)
    assert all(jax.tree.leaves(same))
    # fit-reward-value rolls a randomised run out without its action noise unless asked
    from stride_jax.jobs import fit_reward_value as fit_job
    robust = tmp_path / "robust_run"
    shutil.copytree(run, robust)
    conf = json.loads((robust / "config.json").read_text())
    conf["env"].update(friction_min=0.3, friction_max=1.2, action_noise=0.02)
    (robust / "config.json").write_text(json.dumps(conf))
    seen = []

    class Stop(Exception):
        pass

    def stop(env, *args):
        seen.append((env.cfg.friction_min, env.cfg.friction_max, env.cfg.action_noise))
        raise Stop

    with pytest.MonkeyPatch.context() as monkey:
        monkey.setattr(fit_job.learned_lib, "rollouts", stop)
        for flags in ([], ["--keep-action-noise"]):
            with pytest.raises(Stop):
                cli.main(["fit-reward-value", "--preset", "tiny", "--policy", str(robust),
                          "--out", str(tmp_path / "unused"), *flags])
    assert seen == [(0.3, 1.2, 0.0), (0.3, 1.2, 0.02)]
    out = tmp_path / "learned"
    cli.main(["fit-reward-value", "--preset", "tiny", "--policy", str(run), "--out", str(out)])
    reward, value = learned.load(out / "reward_value.msgpack")
    assert (out / "report.json").is_file() and jax.tree.leaves(reward) and jax.tree.leaves(value)
    # --members: ensembles on the same rollouts, the first member the single fit
    out2 = tmp_path / "learned2"
    cli.main(["fit-reward-value", "--preset", "tiny", "--policy", str(run), "--out", str(out2),
              "--members", "2"])
    rewards, values = learned.load(out2 / "reward_value.msgpack", ensemble=True)
    assert len(rewards) == 2 and len(values) == 2
    for a, b in ((rewards[0], reward), (values[0], value)):
        assert all(jax.tree.leaves(jax.tree.map(lambda x, y: bool(jnp.array_equal(x, y)), a, b)))
    assert any(not jnp.array_equal(x, y) for x, y in
               zip(jax.tree.leaves(rewards[1]), jax.tree.leaves(rewards[0])))
    report = json.loads((out2 / "report.json").read_text())
    assert len(report["members"]) == 2 and report["config"]["members"] == 2
    with pytest.raises(SystemExit, match="members must be >= 1"):
        cli.main(["fit-reward-value", "--preset", "tiny", "--policy", str(run), "--out",
                  str(tmp_path / "unused"), "--members", "0"])
