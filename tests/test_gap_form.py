"""The named effect's form: one value on the slow and the fast half of the logs
(stride_jax.gap.form)."""

import dataclasses

import numpy as np
import pytest

from stride_jax.gap import attribute, calibrate, diagnose, fit, form, nominal, real

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
    assert c["slow_hi"][0] < c["fast_lo"][0]
    assert "its value changes with joint speed" in attribute.verdict(w, TINY)["reason"]


def test_a_damping_of_the_right_form_agrees_on_both_halves(pendulum):
    _, logged = real.generate(pendulum, {"damping": 0.3}, 6, 120, seed=1)
    out = diagnose.diagnose(pendulum, logged, TINY, log=QUIET)
    v, c = out["verdict"], out["which"]["form_check"]
    assert v["effects"] == ["damping"] and v["confident"], v["reason"]
    assert not c["differs"] and abs(c["windows"][0] - c["windows"][1]) <= 2
    for half in ("slow", "fast"):
        assert c[f"{half}_lo"][0] <= c[half][0] <= c[f"{half}_hi"][0]
        assert abs(c[half][0] - 0.3) < 0.01


def test_the_halves_split_the_windows_at_the_median_speed(pendulum):
    _, logged = real.generate(pendulum, None, 3, 60, seed=2)
    data = fit.make_data(logged, 2)
    speed = lambda d: np.abs(d.qd[d.start][:, pendulum.act_dof]).max(1)
    slow, fast, (lo, hi) = form.by_speed(pendulum, data)
    assert lo == hi and len(slow.start) + len(fast.start) == len(data.start)
    assert speed(slow).max() <= lo < speed(fast).min()
    slow, fast, (lo, hi) = form.by_speed(pendulum, data, 1 / 3)  # the slowest and the fastest third
    assert lo < hi and abs(len(slow.start) - len(data.start) / 3) <= 1 and abs(len(fast.start) - len(data.start) / 3) <= 1
    assert speed(slow).max() <= lo and hi < speed(fast).min()
    pair = {"effects": ["damping", "delay"], "params": {"damping": [0.1], "delay": [1.0]}}
    assert form.check(pendulum, data, np.ones(pendulum.mj.nv), pair, TINY.fit, 0.25) is None
