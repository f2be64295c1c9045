"""Training: end to end from the CLI, resumption after a hard kill, and the NaN guard."""

import csv
import dataclasses
import os
import pathlib
import signal
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp
import pytest

from stride_jax import cli
from stride_jax.train import dynamics as train_dynamics
from stride_jax.train import loop

ARGS = ["train", "--robot", "pendulum", "--preset", "tiny", "--hidden", "16", "--steps", "60",
        "--ckpt-every", "10", "--eval-every", "10"]


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    path = tmp_path_factory.mktemp("data") / "pendulum"
    cli.main(["data", "--robot", "pendulum", "--preset", "tiny", "--out", str(path)])
    return path


def _latest_params(run: pathlib.Path):
    mngr = ocp.CheckpointManager(run.absolute() / "ckpt")
    step = mngr.latest_step()
    return step, mngr.restore(step)["params"]


def test_training_runs_and_improves(data_dir, tmp_path):
    run = tmp_path / "run"
    cli.main(ARGS + ["--data", str(data_dir), "--out", str(run)])
    rows = np.genfromtxt(run / "metrics.csv", delimiter=",", names=True)
    assert rows["val_loss"][-1] < rows["val_loss"][0]
    assert (run / "best").is_dir() and (run / "summary.json").exists()
    # A copied run folder with a stale checkpoint beside its best (a later step of another
    # model, here the optimiser-state checkpoint) still loads the best the summary names.
    import shutil

    from stride_jax import dynamics

    copy = tmp_path / "copy"
    shutil.copytree(run, copy)
    stale = max(int(p.name) for p in (run / "ckpt").iterdir() if p.name.isdigit())
    shutil.copytree(run / "ckpt" / str(stale), copy / "best" / "99999")
    (_, want), (_, got) = dynamics.load(run), dynamics.load(copy)
    jax.tree.map(np.testing.assert_array_equal, want, got)


def test_a_killed_run_resumes_to_the_uninterrupted_result(data_dir, tmp_path):
    full, killed = tmp_path / "full", tmp_path / "killed"
    cli.main(ARGS + ["--data", str(data_dir), "--out", str(full)])
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.Popen([sys.executable, "-m", "stride_jax.cli", *ARGS, "--data", str(data_dir),
                             "--out", str(killed)], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 300
    while not (killed / "ckpt" / "20").exists():
        assert proc.poll() is None and time.time() < deadline, "the run died before step 20"
        time.sleep(0.02)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    done = [int(p.name) for p in (killed / "ckpt").iterdir() if p.name.isdigit()]
    assert max(done) < 60, "the run finished before it could be killed"
    cli.main(ARGS + ["--data", str(data_dir), "--out", str(killed)])  # resume
    step_a, a = _latest_params(full)
    step_b, b = _latest_params(killed)
    assert step_a == step_b == 60
    jax.tree.map(lambda x, y: np.testing.assert_allclose(x, y, rtol=1e-5, atol=1e-6), a, b)


def test_nan_loss_stops_with_a_clear_message(tmp_path):
    split = {k: np.ones((2, 5, 1), np.float32) for k in ("q", "qd", "tau", "qdd", "ctrl")}
    split["valid"] = np.ones((2, 5), bool)
    init = lambda key: {"w": jnp.ones(3)}
    loss = lambda p, ex, key: (jnp.sum(p["w"]) * jnp.log(-ex["q"][0]), {})
    cfg = loop.LoopConfig(steps=4, batch=4, eval_every=2, ckpt_every=2)
    with pytest.raises(loop.TrainingError, match="loss became nan by step 2.*learning rate"):
        train_dynamics.train(loss, init, split, split, cfg, tmp_path / "nan")


def test_chunked_steps_take_the_same_draws_as_one_scan():
    """Step i's minibatch and loss key come from fold_in(key, i): two chunks of scan_steps land
    where one scan does (what makes resumption and validation chunking exact)."""
    data = {"x": jnp.linspace(-1.0, 1.0, 50), "y": jnp.linspace(0.0, 3.0, 50)}
    loss = lambda p, b, key: (jnp.mean((p["w"] * b["x"] + p["b"] - b["y"]
                                        + 0.01 * jax.random.normal(key, b["x"].shape)) ** 2), {})
    opt = loop.optimizer(1e-2, 10)
    p0, key = {"w": jnp.zeros(()), "b": jnp.zeros(())}, jax.random.key(0)
    (one, _), losses, _ = loop.scan_steps(loss, opt, p0, opt.init(p0), data, key, 0, 10, 8)
    (p, s), first, _ = loop.scan_steps(loss, opt, p0, opt.init(p0), data, key, 0, 4, 8)
    (two, _), second, _ = loop.scan_steps(loss, opt, p, s, data, key, 4, 6, 8)
    jax.tree.map(np.testing.assert_array_equal, one, two)
    np.testing.assert_array_equal(losses, np.concatenate([first, second]))
    # the host loop without validation returns the last parameters, and every step's loss
    cfg = loop.LoopConfig(steps=10, batch=8, eval_every=3)
    res = loop.run(loss, p0, data, cfg, opt, key, progress=None)
    assert res.best_step == 10 and len(res.losses) == 10
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-6), res.params, one)


def test_stop_at_holds_a_run_at_that_step_on_the_full_schedule(tmp_path):
    """``stop_at`` stops a run validated and saved at that step (off the validation grid too);
    the same call again adds nothing, and going on lands where one uninterrupted run does: the
    schedule spans ``steps`` throughout (seeds trained to where another seed stopped)."""
    data = {"x": jnp.linspace(-1.0, 1.0, 50), "y": jnp.linspace(0.0, 3.0, 50)}
    loss = lambda p, b, key: (jnp.mean((p["w"] * b["x"] + p["b"] - b["y"]) ** 2), {})
    validate = lambda p: (float(jnp.mean((p["w"] * data["x"] + p["b"] - data["y"]) ** 2)), {})
    opt = loop.optimizer(1e-2, 10)
    p0, key = {"w": jnp.zeros(()), "b": jnp.zeros(())}, jax.random.key(0)
    (one, _), _, _ = loop.scan_steps(loss, opt, p0, opt.init(p0), data, key, 0, 10, 8)
    run = lambda stop_at: loop.run(loss, p0, data, loop.LoopConfig(
        steps=10, batch=8, eval_every=3, ckpt_every=3, stop_at=stop_at), opt, key, validate,
        out=tmp_path / "run", progress=None)
    held = run(4)
    assert held.steps_done == 4 and held.checked_at == [3, 4]
    assert run(4).steps_done == 4 and run(4).checked_at == []
    assert run(0).steps_done == 10
    step, last = _latest_params(tmp_path / "run")
    assert step == 10
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-6), last, one)


@pytest.mark.parametrize("bad, says", [
    (dict(steps=0), "loop.steps=0: need a positive integer"),
    (dict(eval_every=0), "loop.eval_every=0: need a positive integer"),
    (dict(batch=2.5), "loop.batch=2.5: need a positive integer"),
    (dict(stop_at=-1), "loop.stop_at=-1: need a step count >= 0"),
    (dict(lr=float("nan")), "loop.lr=nan: need a positive, finite learning rate"),
    (dict(lr=0.0), "loop.lr=0.0: need a positive"),
])
def test_bad_loop_settings_are_clear_errors(bad, says):
    with pytest.raises(ValueError, match=says.replace(".", r"\.")):
        loop.LoopConfig(**bad)


def test_missing_dataset_says_how_to_make_it(tmp_path):
    """Training makes no data unless asked (--make-data): the error names the command."""
    with pytest.raises(SystemExit, match="stride data --robot pendulum --preset tiny"):
        cli.main(["train", "--robot", "pendulum", "--preset", "tiny",
                  "--data", str(tmp_path / "none"), "--out", str(tmp_path / "run")])
    assert not (tmp_path / "none").exists()
    with pytest.raises(SystemExit, match="unknown robot 'g3'"):  # not "no dataset at data/g3"
        cli.main(["train", "--robot", "g3", "--preset", "tiny", "--out", str(tmp_path / "run")])
    with pytest.raises(SystemExit, match="unknown model 'strde'"):  # before making data for it
        cli.main(["train", "--robot", "pendulum", "--model", "strde", "--preset", "tiny", "--make-data",
                  "--data", str(tmp_path / "none"), "--out", str(tmp_path / "run")])
    assert not (tmp_path / "none").exists()


def test_train_flags_nest_the_library_configs_with_the_flat_flags_kept():
    """`stride train` derives `--net.*` from MLPConfig and `--loop.*` from LoopConfig; the flat
    flags of earlier commands set the same fields; presets are instances; to_flags round-trips."""
    import argparse
    import dataclasses

    from stride_jax import config
    from stride_jax.dynamics.mlp import MLPConfig
    from stride_jax.jobs import train as job

    parser = argparse.ArgumentParser()
    config.add_flags(parser, job.TrainConfig)
    new = config.from_flags(job.TrainConfig, parser.parse_args(
        ["--net.hidden", "64", "--net.init", "orthogonal", "--loop.steps", "30", "--loop.lr", "3e-3",
         "--loop.eval-every", "10", "--loop.seed", "2"]), job.PRESETS["tiny"])
    old = config.from_flags(job.TrainConfig, parser.parse_args(
        ["--hidden", "64", "--weight-init", "orthogonal", "--steps", "30", "--lr", "3e-3",
         "--eval-every", "10", "--seed", "2"]), job.PRESETS["tiny"])
    assert new == old
    assert new.net == MLPConfig(hidden=64, depth=2, init="orthogonal")
    assert (new.loop.steps, new.loop.batch, new.loop.lr, new.loop.eval_every, new.loop.seed) == (
        30, 64, 3e-3, 10, 2)
    assert job.TrainConfig().net == MLPConfig()  # one source of the networks' defaults
    assert job.PRESETS["default"].net.hidden == 128
    assert job.PRESETS["paper"].loop == dataclasses.replace(
        loop.LoopConfig(), steps=12_000, batch=1024, eval_every=1000, ckpt_every=2000)
    flags = config.to_flags(new)
    assert config.from_flags(job.TrainConfig, parser.parse_args(flags)) == new


def test_a_batch_loss_takes_the_training_steps_and_validation_stays_per_example(tmp_path):
    """``batch_loss`` (a model's minibatch loss, ``Model.batch_loss``) is what the training steps
    minimise; validation keeps the per-example loss' mean: a batch loss that pulls ``w`` to 2
    while the per-example loss pulls it to 0 ends near 2, and the logged validation loss is the
    per-example one at the end."""
    split = {k: np.ones((2, 5, 1), np.float32) for k in ("q", "qd", "tau", "qdd", "ctrl")}
    split["valid"] = np.ones((2, 5), bool)
    init = lambda key: {"w": jnp.zeros(())}
    loss = lambda p, ex, key: (p["w"] ** 2, {"select": p["w"] ** 2})
    batch = lambda p, ex, keys: ((p["w"] - 2.0) ** 2, {"select": (p["w"] - 2.0) ** 2})
    cfg = loop.LoopConfig(steps=300, batch=4, eval_every=300, ckpt_every=300, lr=0.05)
    out = tmp_path / "batch"
    train_dynamics.train(loss, init, split, split, cfg, out, log=lambda *_: None,
                         batch_loss=batch)
    last = list(csv.DictReader(open(out / "metrics.csv")))[-1]
    assert abs(float(last["val_loss"]) - 4.0) < 0.2  # w near 2, scored by the per-example loss


def _noisy_line():
    data = {"x": jnp.linspace(-1.0, 1.0, 50), "y": jnp.linspace(0.0, 3.0, 50)}
    loss = lambda p, b, key: (jnp.mean((p["w"] * b["x"] + p["b"] - b["y"]
                                        + 0.1 * jax.random.normal(key, b["x"].shape)) ** 2), {})
    validate = lambda p: (float(jnp.mean((p["w"] * data["x"] + p["b"] - data["y"]) ** 2)),
                          {"w": float(p["w"])})
    return data, loss, validate


def test_runs_side_by_side_are_each_run_alone(tmp_path):
    """``run_many`` trains each run as ``run`` does with its own start and draws (to float
    rounding), each into its own folder with its own best step; a side-by-side run held by
    ``stop_at`` goes on from its checkpoints to the same end, and a single ``run`` into one of the
    folders finds it finished."""
    data, loss, validate = _noisy_line()
    opt = loop.optimizer(3e-2, 12)
    starts = [{"w": jnp.array(s), "b": jnp.array(-s)} for s in (0.0, 2.0)]
    keys = [jax.random.key(3), jax.random.key(4)]
    cfg = loop.LoopConfig(steps=12, batch=8, eval_every=3, ckpt_every=3)
    alone = [loop.run(loss, p, data, cfg, opt, k, validate, out=tmp_path / f"alone{i}", progress=None)
             for i, (p, k) in enumerate(zip(starts, keys))]
    outs = [tmp_path / "many-a", tmp_path / "many-b"]
    held = loop.run_many(loss, starts, data, dataclasses.replace(cfg, stop_at=5), opt, keys, validate,
                         outs=outs, progress=None)
    assert [r.steps_done for r in held] == [5, 5]
    many = loop.run_many(loss, starts, data, cfg, opt, keys, validate, outs=outs, progress=None)
    for i, (a, m, out) in enumerate(zip(alone, many, outs)):
        assert m.steps_done == 12 and m.checked_at == [6, 9, 12]
        np.testing.assert_allclose(m.scores, a.scores[1:], rtol=1e-5)
        (step_a, pa), (step_m, pm) = _latest_params(tmp_path / f"alone{i}"), _latest_params(out)
        assert step_a == step_m == 12
        jax.tree.map(lambda x, y: np.testing.assert_allclose(x, y, rtol=1e-5, atol=1e-6), pm, pa)
        rows = list(csv.DictReader(open(out / "metrics.csv")))
        assert [int(r["step"]) for r in rows] == [3, 5, 6, 9, 12]
        again = loop.run(loss, starts[0], data, cfg, opt, keys[0], validate, out=out, progress=None)
        assert again.steps_done == 12 and again.checked_at == []
    assert abs(float(many[0].params["w"]) - float(many[1].params["w"])) > 1e-3  # two runs, not one twice


def test_runs_side_by_side_validate_all_at_once_as_one_by_one(tmp_path):
    """``validate_all`` (every run's validation from the stacked parameters, one program) gives
    each run the scores, best step and parameters that validating the runs in turn gives; the
    result says where the time went."""
    data, loss, validate = _noisy_line()
    opt = loop.optimizer(3e-2, 9)
    starts = [{"w": jnp.array(s), "b": jnp.array(-s)} for s in (0.0, 2.0, -1.0)]
    keys = [jax.random.key(k) for k in (3, 4, 5)]
    cfg = loop.LoopConfig(steps=9, batch=8, eval_every=3, ckpt_every=3)
    mse = jax.jit(jax.vmap(lambda p: jnp.mean((p["w"] * data["x"] + p["b"] - data["y"]) ** 2)))

    def at_once(params):
        return np.asarray(mse(params)), [{"w": float(w)} for w in params["w"]]

    each = loop.run_many(loss, starts, data, cfg, opt, keys, validate, outs=[tmp_path / f"e{i}" for i in range(3)],
                         progress=None)
    once = loop.run_many(loss, starts, data, cfg, opt, keys, outs=[tmp_path / f"o{i}" for i in range(3)],
                         progress=None, validate_all=at_once)
    for e, o in zip(each, once):
        np.testing.assert_allclose(o.scores, e.scores, rtol=1e-6)
        assert o.best_step == e.best_step and o.checked_at == e.checked_at == [3, 6, 9]
        np.testing.assert_allclose(o.params["w"], e.params["w"], rtol=1e-6)
        assert set(o.seconds) == {"train", "validate", "save", "other"} and all(v >= 0 for v in o.seconds.values())
    w = [[float(r["w"]) for r in csv.DictReader(open(tmp_path / f"{k}2" / "metrics.csv"))] for k in "eo"]
    assert len(w[0]) == 3 and w[1] == pytest.approx(w[0], rel=1e-6)  # each run's own metrics row
    with pytest.raises(ValueError, match="not both"):
        loop.run_many(loss, starts, data, cfg, opt, keys, validate, progress=None, validate_all=at_once)
    with pytest.raises(ValueError, match="returned 2 scores and 2 metrics for 3 runs"):
        loop.run_many(loss, starts, data, cfg, opt, keys, progress=None,
                      validate_all=lambda p: (np.zeros(2), [{}, {}]))


def test_the_best_parameters_are_written_with_the_checkpoints(tmp_path, monkeypatch):
    """A best found at a validation is written to ``best`` with the next checkpoint, not at once
    (a run resumed from that checkpoint finds any later best again): here at most one best write
    per checkpoint, alone and side by side, and the best on disk is the returned one."""
    data, loss, validate = _noisy_line()
    opt = loop.optimizer(3e-2, 12)
    starts = [{"w": jnp.array(s), "b": jnp.array(-s)} for s in (0.0, 2.0)]
    cfg = loop.LoopConfig(steps=12, batch=8, eval_every=1, ckpt_every=6)
    writes = []
    manager = loop._manager

    def counted(path, keep):
        m = manager(path, keep)
        save = m.save
        m.save = lambda step, *a, **k: (writes.append((path.parent.name, path.name, step)), save(step, *a, **k))[1]
        return m

    monkeypatch.setattr(loop, "_manager", counted)
    alone = loop.run(loss, starts[1], data, cfg, opt, jax.random.key(4), validate, out=tmp_path / "r", progress=None)
    many = loop.run_many(loss, starts, data, cfg, opt, [jax.random.key(3), jax.random.key(4)], validate,
                         outs=[tmp_path / "a", tmp_path / "b"], progress=None)
    for run_dir, res in (("r", alone), ("a", many[0]), ("b", many[1])):
        bests = [s for d, kind, s in writes if d == run_dir and kind == "best"]
        assert 1 <= len(bests) <= 2 and bests[-1] == res.best_step  # checkpoints at 6 and 12
        assert len(res.checked_at) == 12
        mngr = ocp.CheckpointManager((tmp_path / run_dir / "best").absolute())
        assert mngr.latest_step() == res.best_step
        p = mngr.restore(res.best_step)
        jax.tree.map(lambda x, y: np.testing.assert_allclose(x, y), p, res.params)


def test_runs_side_by_side_name_the_run_whose_loss_fails(tmp_path):
    data, _, validate = _noisy_line()
    loss = lambda p, b, key: (jnp.mean(jnp.log(p["w"]) * b["x"] ** 2), {})
    starts = [{"w": jnp.array(1.0), "b": jnp.array(0.0)}, {"w": jnp.array(-1.0), "b": jnp.array(0.0)}]
    cfg = loop.LoopConfig(steps=4, batch=8, eval_every=2, ckpt_every=2)
    with pytest.raises(loop.TrainingError, match="run 1 of 2: the training loss became nan by step 2"):
        loop.run_many(loss, starts, data, cfg, loop.optimizer(1e-2, 4), [jax.random.key(0)] * 2, validate,
                      outs=[tmp_path / "a", tmp_path / "b"], progress=None)
    with pytest.raises(ValueError, match="2 parameter sets, 1 keys"):
        loop.run_many(loss, starts, data, cfg, loop.optimizer(1e-2, 4), [jax.random.key(0)], progress=None)


def test_train_seeds_side_by_side_is_each_seed_alone(data_dir, tmp_path):
    """``stride train --seeds 0,1`` leaves ``<out>-s0`` and ``<out>-s1``, each the run that
    ``--seed`` alone makes (to float rounding), loadable as any run."""
    from stride_jax import dynamics

    short = ARGS + ["--steps", "20", "--data", str(data_dir)]
    cli.main(short + ["--out", str(tmp_path / "run"), "--seeds", "0,1"])
    cli.main(short + ["--out", str(tmp_path / "alone"), "--seed", "1"])
    (_, side), (_, alone) = dynamics.load(tmp_path / "run-s1"), dynamics.load(tmp_path / "alone")
    jax.tree.map(lambda x, y: np.testing.assert_allclose(x, y, rtol=1e-4, atol=1e-5), side, alone)
    (_, first) = dynamics.load(tmp_path / "run-s0")
    assert not np.allclose(jax.tree.leaves(first)[0], jax.tree.leaves(side)[0])
    cfg = __import__("json").loads((tmp_path / "run-s1" / "config.json").read_text())
    assert cfg["train"]["loop"]["seed"] == 1 and cfg["side_by_side"] == [0, 1]
    with pytest.raises(SystemExit, match="--seeds"):
        cli.main(short + ["--out", str(tmp_path / "x"), "--seeds", "0,0"])
    with pytest.raises(SystemExit, match="--seed 3 with --seeds 0,1"):
        cli.main(short + ["--out", str(tmp_path / "x"), "--seeds", "0,1", "--seed", "3"])


def test_runs_side_by_side_resume_at_the_step_all_their_checkpoints_hold(tmp_path):
    """A run saved further than the others (killed between their saves, or trained on alone) is
    taken back to the last step every run holds, and the side-by-side runs end where they would
    have ended uninterrupted."""
    data, loss, validate = _noisy_line()
    opt = loop.optimizer(3e-2, 9)
    starts = [{"w": jnp.array(s), "b": jnp.array(-s)} for s in (0.0, 2.0)]
    keys = [jax.random.key(3), jax.random.key(4)]
    cfg = loop.LoopConfig(steps=9, batch=8, eval_every=3, ckpt_every=3)
    outs, whole = [tmp_path / "a", tmp_path / "b"], [tmp_path / "wa", tmp_path / "wb"]
    loop.run_many(loss, starts, data, cfg, opt, keys, validate, outs=whole, progress=None)
    loop.run_many(loss, starts, data, dataclasses.replace(cfg, stop_at=3), opt, keys, validate, outs=outs,
                  progress=None)
    loop.run(loss, starts[0], data, dataclasses.replace(cfg, stop_at=6), opt, keys[0], validate, out=outs[0],
             progress=None)  # run a now one save ahead of run b
    said = []
    loop.run_many(loss, starts, data, cfg, opt, keys, validate, outs=outs, log=said.append, progress=None)
    assert "resumed 2 runs from step 3" in said
    for out, ref in zip(outs, whole):
        (step, p), (step_ref, p_ref) = _latest_params(out), _latest_params(ref)
        assert step == step_ref == 9
        jax.tree.map(lambda x, y: np.testing.assert_allclose(x, y, rtol=1e-6), p, p_ref)
