"""The named effect's form: one value where each joint moves slowest and fastest
(stride_jax.gap.form)."""

import dataclasses

import numpy as np
import pytest

from stride_jax.gap import attribute, calibrate, diagnose, fit, form, nominal, real
from stride_jax.jobs import gap_report as report

TINY = dataclasses.replace(diagnose.PRESETS["tiny"], progress=False, calibrate=calibrate.CalibrateConfig(mode="off"))
QUIET = lambda s: None


@pytest.fixture(scope="module")
def pendulum():
    return nominal.load("pendulum")


def test_a_quadratic_drag_named_as_damping_is_not_confident(pendulum):
    # the library has no quadratic drag: linear damping imitates it (94% of the gap), with a
    # damping that grows with speed. On the pendulum the structure rule already withholds
    # confidence (|qd| qd is left in the residual), so the form check's two fits are skipped ...
    _, logged = real.generate(pendulum, {"quadratic_drag": 0.05}, 6, 120, seed=1)
    out = diagnose.diagnose(pendulum, logged, TINY, log=QUIET)
    v = out["verdict"]
    assert v["verdict"] == "explained" and v["effects"] == ["damping"] and not v["confident"], v["reason"]
    assert out["which"]["form_check"] is None and "the fit leaves structure" in v["reason"]
    # ... and where the other rules would have been confident, the form check decides: the slowest
    # and the fastest windows disagree, and the reason says why
    w = dict(out["which"])
    c = attribute.check_form(pendulum, fit.make_data(logged, TINY.steps), np.ones(pendulum.mj.nv), w,
                             dict(v, confident=True), TINY, QUIET)
    assert c is w["form_check"] and c["differs"] and c["fast"][0] > 1.5 * c["slow"][0], c
    assert c["intervals"] and c["slow_hi"][0] < c["fast_lo"][0]
    assert c["slow_lo"][0] <= c["slow"][0] <= c["slow_hi"][0] and c["fast_lo"][0] <= c["fast"][0] <= c["fast_hi"][0]
    assert "its value changes with joint speed" in attribute.verdict(w, TINY)["reason"]


def test_a_damping_of_the_right_form_agrees_on_both_halves(pendulum, tmp_path):
    _, logged = real.generate(pendulum, {"damping": 0.3}, 6, 120, seed=1)
    out = diagnose.diagnose(pendulum, logged, TINY, log=QUIET)
    v, c = out["verdict"], out["which"]["form_check"]
    assert v["effects"] == ["damping"] and v["confident"], v["reason"]
    assert not c["differs"] and c["split"] == "per joint" and c["windows"] == out["which"]["fit_windows"]
    for half in ("slow", "fast"):
        assert abs(c[half][0] - 0.3) < 0.01
    # within 25% of each other they agree whatever their intervals, which are not profiled
    assert not c["intervals"] and c["slow_lo"] is None and c["fast_hi"] is None
    md = report.write(out, tmp_path).read_text()  # the report says what the check found
    assert "Form check (damping refitted where each joint moves slowest" in md and "they agree" in md
    assert "their intervals were not needed" in md


def test_the_split_is_per_joint_speed(pendulum):
    _, logged = real.generate(pendulum, None, 3, 60, seed=2)
    data = fit.make_data(logged, 2)
    j = pendulum.act_dof[0]
    rows = data.start[:, None] + np.arange(data.k + 1)
    speed = np.sqrt((data.qd[rows][:, :, j] ** 2).mean(1))  # over the replay window
    slow, fast, (lo, hi) = form.by_joint_speed(pendulum, data)  # the slowest and the fastest third
    assert slow.shape == fast.shape == (len(data.start), pendulum.mj.nv)
    assert lo[j] < hi[j]
    assert abs(slow[:, j].sum() - len(data.start) / 3) <= 1 and abs(fast[:, j].sum() - len(data.start) / 3) <= 1
    assert speed[slow[:, j] > 0].max() <= lo[j] and hi[j] < speed[fast[:, j] > 0].min()
    assert not (slow * fast).any()
    pair = {"effects": ["damping", "delay"], "params": {"damping": [0.1], "delay": [1.0]}}
    assert form.check(pendulum, data, np.ones(pendulum.mj.nv), pair, TINY.fit, 0.25) is None


def test_the_split_goes_by_each_joint_not_the_window():
    # two joints out of phase: one window has one joint fast and the other slow; a per-window
    # split (by RMS speed) would put both entries on the same side
    import types
    sm = types.SimpleNamespace(act_dof=np.array([0, 1]), mj=types.SimpleNamespace(nv=2))
    t = np.linspace(0, 4 * np.pi, 300)
    qd = np.stack([np.sin(t), np.cos(t)], 1)
    data = types.SimpleNamespace(qd=qd, start=np.arange(299), k=1)
    slow, fast, _ = form.by_joint_speed(sm, data)
    both = (slow[:, 0] > 0) & (fast[:, 1] > 0)
    assert both.sum() > 50  # joint 0 slow where joint 1 is fast
    assert np.abs(qd[:299][slow[:, 0] > 0, 0]).max() < np.abs(qd[:299][fast[:, 0] > 0, 0]).min()


def test_a_mask_of_the_wrong_shape_is_named(pendulum):
    _, logged = real.generate(pendulum, None, 2, 30, seed=3)
    data = fit.make_data(logged, 1)
    with pytest.raises(ValueError, match="mask has shape"):
        fit.Objective(pendulum, data, np.ones(pendulum.mj.nv), ("damping",), mask=np.ones((3, 7)))


def test_fits_that_differ_only_in_their_mask_share_replays_and_give_the_same_fits(pendulum, monkeypatch):
    _, logged = real.generate(pendulum, {"damping": 0.3}, 3, 60, seed=4, noise=real.SensorNoise())
    data = fit.make_data(logged, 3)
    scale = diagnose.scale_of(pendulum, data)
    slow, fast, _ = form.by_joint_speed(pendulum, data)
    cfg = TINY.fit
    alone = [fit.fit(pendulum, data, scale, ("damping",), cfg, mask=m) for m in (slow, fast)]
    replayed = []
    real_residuals = fit.replay.residuals
    monkeypatch.setattr(fit.replay, "residuals", lambda sm, plans, *a, **k: (
        replayed.append(len(plans)), real_residuals(sm, plans, *a, **k))[1])
    shared: dict = {}
    together = [fit.fit(pendulum, data, scale, ("damping",), cfg, mask=m, cache=shared) for m in (slow, fast)]
    for a, b in zip(alone, together):
        for field in ("params", "lo", "hi"):
            np.testing.assert_array_equal(getattr(a, field)["damping"], getattr(b, field)["damping"])
        assert a.train_loss == b.train_loss
    # the grid (grid points and the nominal value) was replayed once for both fits
    assert replayed.count(cfg.grid + 1) == 1 and 0 not in replayed, replayed
