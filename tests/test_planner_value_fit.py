"""experiments/planner_value_fit.py: the closed loop's planner flags and the value's reach the
refit (``dreamer_mpc.train_value``) as given; what it cannot run is named before any work."""

import pytest


def test_flags_reach_the_planner_and_the_value(experiment, monkeypatch):
    mod = experiment("planner_value_fit")
    from stride_jax.jobs import dreamer_mpc

    seen = {}

    def train_value(cl, vcfg, name, run, out, command):
        seen.update(cl=cl, vcfg=vcfg, name=name, run=run, out=out, command=command)
        return {}

    monkeypatch.setattr(dreamer_mpc, "train_value", train_value)
    mod.main(["--robot", "g1", "--models", "stride=runs/m", "--policy", "runs/p",
              "--learned", "l.msgpack", "--mppi.samples", "64", "--mppi.family-samples", "24",
              "--planning.learned-track-weight", "10", "--value.worlds", "6",
              "--value.seconds", "2", "--out", "runs/v"])
    cl, v = seen["cl"], seen["vcfg"]
    assert (cl.robot, cl.policy, cl.learned, cl.out) == ("g1", "runs/p", "l.msgpack", "runs/v")
    assert (cl.mppi.samples, cl.mppi.family_samples) == (64, 24)
    assert cl.planning.learned_track_weight == 10
    assert (v.worlds, v.seconds) == (6, 2.0)
    assert (seen["name"], seen["run"], seen["out"]) == ("stride", "runs/m", "runs/v")
    assert "--value.worlds 6" in seen["command"]


def test_what_it_cannot_refit_is_named(experiment):
    mod = experiment("planner_value_fit")
    base = ["--policy", "runs/p", "--learned", "l.msgpack", "--out", "runs/v"]
    with pytest.raises(SystemExit, match="the one learned model"):
        mod.parse(["--models", "stride=a,delan=b", *base])
    with pytest.raises(SystemExit, match="the one learned model"):
        mod.parse(["--models", "oracle", *base])
    with pytest.raises(SystemExit, match="--policy and --learned"):
        mod.parse(["--models", "stride=a", "--out", "runs/v"])
