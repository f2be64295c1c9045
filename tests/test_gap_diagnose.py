"""The diagnosis recovers planted effects; the CLI writes a report and rejects bad logs."""

import dataclasses
import json

import pytest

from stride_jax.gap import diagnose, fit, logs, real
from stride_jax.jobs import gap as cli
from stride_jax.sim import model


def test_pendulum_damping_recovered_within_5_percent_from_noisy_logs():
    sm = model.load("pendulum")
    true = 0.3
    _, logged = real.generate(sm, {"damping": true}, 6, 150, seed=2, noise=real.SensorNoise())
    cfg = diagnose.PRESETS["tiny"]
    out = diagnose.diagnose(sm, logged, cfg, log=lambda s: None)
    best = out["which"]["ranking"][0]
    assert out["verdict"]["verdict"] == "explained" and best["effects"] == ["damping"]
    assert abs(best["params"]["damping"][0] - true) < 0.05 * true
    assert best["param_lo"]["damping"][0] <= best["params"]["damping"][0] <= best["param_hi"]["damping"][0]
    assert out["how_far"]["gap_after"] < out["how_far"]["gap_before"]


def test_ranking_puts_a_planted_go1_effect_first(go1):
    _, logged = real.generate(go1, {"damping": 1.5}, 3, 30, seed=0)
    cfg = dataclasses.replace(
        diagnose.PRESETS["tiny"], steps=1, pairs_of=0, horizon=5, windows=1,
        fit=fit.FitConfig(grid=5, profile=0, bootstrap=50, refits=0, max_nfev=3))
    out = diagnose.diagnose(go1, logged, cfg, log=lambda s: None)
    ranking = out["which"]["ranking"]
    assert ranking[0]["effects"] == ["damping"], [(r["effects"], r["explained"]) for r in ranking[:3]]
    assert abs(ranking[0]["params"]["damping"][0] - 1.5) < 0.15
    assert ranking[0]["explained"] > ranking[1]["explained"]
    assert out["verdict"]["effects"] == ["damping"]
    assert set(out["where"]["per_foot_phase"]) == {"FR", "FL", "RR", "RL"}


def test_cli_simulate_diagnose_report(tmp_path, capsys):
    logdir, outdir = tmp_path / "logs", tmp_path / "out"
    assert cli.main(["simulate", "--robot", "pendulum", "--out", str(logdir), "--effects",
                     '{"delay": 2}', "--trajectories", "4", "--steps", "80"]) == 0
    assert cli.main(["diagnose", "--robot", "pendulum", "--logs", str(logdir), "--out", str(outdir),
                     "--preset", "tiny", "--horizon", "10"]) == 0
    d = json.loads((outdir / "diagnosis.json").read_text())
    assert d["verdict"]["effects"] == ["delay"] and d["config"]["horizon"] == 10
    md = (outdir / "report.md").read_text()
    assert "## Where" in md and "## Which" in md and "## How far" in md
    for png in ("residual_per_dof.png", "ranking.png", "divergence.png"):
        assert (outdir / png).stat().st_size > 1000
    # a log for another robot is refused with a clear message and exit code 2
    assert cli.main(["diagnose", "--robot", "pendulum_bouncing", "--logs", str(logdir), "--out",
                     str(outdir)]) == 2
    assert "log is for robot 'pendulum'" in capsys.readouterr().err
    # planted effects that are not JSON, not an object, or not in the library: named, exit code 2
    for bad, says in (("{delay: 2}", "is not JSON"), ("[2]", "must be a JSON object"),
                      ('{"dampng": 0.3}', "unknown effect(s) ['dampng']")):
        assert cli.main(["simulate", "--robot", "pendulum", "--out", str(tmp_path / "bad"),
                         "--effects", bad]) == 2
        assert says in capsys.readouterr().err, bad
    assert not (tmp_path / "bad").exists()


def test_too_few_trajectories_is_a_clear_error():
    with pytest.raises(ValueError, match="at least 2 trajectories"):
        diagnose.split(1, 0.3, 0)
    with pytest.raises(logs.LogError):
        logs.write("/tmp/unused_gap_dir", model.load("pendulum"), [])


def test_pair_is_named_when_one_effect_is_not_enough():
    # damping masks the delay (the delay alone fits to zero): the conditional screen on top of the
    # best single finds it, and the paired held-out test prefers the pair
    sm = model.load("pendulum")
    _, logged = real.generate(sm, {"damping": 0.3, "delay": 2}, 6, 120, seed=1)
    out = diagnose.diagnose(sm, logged, diagnose.PRESETS["tiny"], log=lambda s: None)
    w = out["which"]
    assert set(out["verdict"]["effects"]) == {"damping", "delay"}, out["verdict"]
    best = w["ranking"][0]
    assert best["vs_best_single"]["preferred"] and best["vs_best_single"]["gain_lower"] > 0
    single = next(r for r in w["ranking"] if r["effects"] == w["best_single"])
    assert best["explained"] > single["explained"]
    assert round(best["params"]["delay"][0]) == 2


def test_small_effect_in_noise_detected_and_control_is_not():
    sm = model.load("pendulum")
    cfg = diagnose.PRESETS["tiny"]
    verdicts = {}
    for name, applied in (("control", {}), ("friction", {"frictionloss": 0.15})):
        _, logged = real.generate(sm, applied, 8, 150, seed=1, noise=real.SensorNoise())
        out = diagnose.diagnose(sm, logged, cfg, log=lambda s: None)
        verdicts[name] = out["verdict"]
        det = out["which"]["detection"]
        assert 0 < det["p_value"] <= 1 and det["level"] < cfg.alpha
    assert verdicts["control"]["verdict"] == "no significant gap", verdicts["control"]
    assert verdicts["friction"]["effects"] == ["frictionloss"], verdicts["friction"]
    # the reasons name the rule that made the call; ties are listed whatever the verdict
    assert "does not beat the nominal model" in verdicts["control"]["reason"]
    assert "needs <" in verdicts["control"]["reason"]
    assert "50% rule" in verdicts["friction"]["reason"] and "15%" in verdicts["friction"]["reason"]
    assert all(isinstance(v["indistinguishable_from"], list) for v in verdicts.values())


def test_an_effect_that_is_not_the_identity_at_its_nominal_value_stops_the_diagnosis(monkeypatch):
    from stride_jax.gap import effects

    sm = model.load("pendulum")
    _, logged = real.generate(sm, {"damping": 0.3}, 3, 40, seed=2)
    # a wrong effect implementation: "damping" at its nominal value adds 0.2 N m s/rad
    monkeypatch.setitem(effects.LIBRARY, "damping", dataclasses.replace(effects.LIBRARY["damping"], nominal=(0.2,)))
    cfg = dataclasses.replace(diagnose.PRESETS["tiny"], calibrate=dataclasses.replace(
        diagnose.PRESETS["tiny"].calibrate, mode="off"), nominal_check=20, progress=False)
    with pytest.raises(RuntimeError, match="do not reproduce the nominal model.*'damping'"):
        diagnose.diagnose(sm, logged, cfg, log=lambda s: None)


def test_a_noise_level_given_with_the_logs_sets_the_floor_to_what_the_noise_adds(tmp_path):
    """With the logged velocities' noise level known, the held-out data carry the floor it gives
    (its variance in each replay's target plus its effect through the replay's start, by replaying
    with more of it), and that floor is what the noise adds to the gap of the same replays over the
    clean twin of the logs; the residuals' autocovariance is the fallback. The diagnosis says which
    it used; a level of the wrong shape is refused; the CLI reads it from the log header."""
    import numpy as np
    from stride_jax.gap import effects, regions
    sm = model.load("pendulum")
    noise = real.SensorNoise(encoder_bits=0, encoder_std=0.0, velocity_std=0.05, torque_std=0.0,
                             outlier_rate=0.0)
    clean, logged = real.generate(sm, {"damping": 0.3}, 6, 150, seed=3, noise=noise)
    cfg = diagnose.PRESETS["tiny"]
    std = np.full(sm.mj.nv, 0.05)
    pn, pc = diagnose.prepare(sm, logged, cfg, std), diagnose.prepare(sm, clean, cfg)
    assert diagnose.prepare(sm, logged, cfg).test_k.noise_floor is None
    nom = effects.build(pn.sm)
    for split in ("test_k", "test"):
        dn, dc = getattr(pn, split), getattr(pc, split)
        adds = fit.gap(fit.residual(pn.sm, nom, dn, pn.scale)) - fit.gap(fit.residual(pn.sm, nom, dc, pn.scale))
        assert 0.7 < dn.noise_floor / adds < 1.4, (split, dn.noise_floor, adds)
        assert regions.noise_floor(np.zeros((3, sm.mj.nv)), dn) == dn.noise_floor  # given, not read off r
    out = diagnose.diagnose(sm, logged, cfg, log=lambda s: None, velocity_std=std)
    assert out["noise_floor"]["source"] == "the velocity noise given with the logs"
    assert out["noise_floor"]["heldout_k_step"] == pn.test_k.noise_floor
    assert "autocovariance" in diagnose.diagnose(sm, logged, cfg, log=lambda s: None)["noise_floor"]["source"]
    with pytest.raises(ValueError, match="velocity_std must be 1 finite numbers"):
        diagnose.prepare(sm, logged, cfg, np.array([0.05, 0.05]))
    # the command line: the level in the log header reaches the diagnosis
    logdir, outdir = tmp_path / "logs", tmp_path / "out"
    logs.write(logdir, sm, logged, velocity_noise={"qd": 0.05})
    assert cli.main(["diagnose", "--robot", "pendulum", "--logs", str(logdir), "--out", str(outdir),
                     "--preset", "tiny"]) == 0
    d = json.loads((outdir / "diagnosis.json").read_text())
    assert d["noise_floor"]["velocity_std"] == [0.05]
