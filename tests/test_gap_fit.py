"""Parameter fits: intervals contain the estimate, respect the bounds and cover the truth; unstable
parameter values are scored as bad fits without MuJoCo's warnings; verdicts name their rule."""

import dataclasses

import numpy as np
from scipy import optimize
import pytest

from stride_jax.gap import attribute, diagnose, effects, filters, fit, real, sim
from stride_jax.sim import model

CFG = diagnose.PRESETS["tiny"]


@pytest.fixture(scope="module")
def pend():
    return model.load("pendulum")


def _data(sm, applied, n, steps, seed, noise=True):
    _, logged = real.generate(sm, applied, n, steps, seed=seed, noise=real.SensorNoise() if noise else None)
    logged = [filters.preprocess(t, sm.robot.ctrl_dt, CFG.preprocess)[0] for t in logged]
    data = fit.make_data(logged, CFG.steps)
    return data, diagnose.scale_of(sm, data)


def test_damping_interval_covers_the_truth_in_repeated_noisy_draws(pend):
    # 20 draws of 4 x 100 noisy steps; the 90% profile interval must contain its estimate, stay in
    # the bounds and cover the planted value in about 90% of draws (measured: 26/30 while the line
    # search stopped at the grid's tolerance, a +0.6 standard-error offset read then as noise bias;
    # 30 draws before session 71, 20 for the suite's time: results/gap_coverage/ has the long run)
    true, hits, draws = 0.3, 0, 20
    lo_b, hi_b = (float(b[0]) for b in effects.ALL["damping"].bounds(pend))
    for seed in range(draws):
        data, scale = _data(pend, {"damping": true}, 4, 100, 1000 + seed)
        f = fit.fit(pend, data, scale, ("damping",), CFG.fit)
        x, lo, hi = f.params["damping"][0], f.lo["damping"][0], f.hi["damping"][0]
        assert lo_b <= lo <= x <= hi <= hi_b, (seed, lo, x, hi)
        hits += lo <= true <= hi
    assert 0.75 <= hits / draws <= 1.0, hits


def test_a_limit_reached_in_few_blocks_gets_an_interval_that_covers_it(pend):
    # torque_limit 0.7 on 4 x 100 noisy steps: the limit is reached in 0-5 of 16 blocks, the
    # estimates spread over 0.27-1.0 across draws, and the sandwich/profile interval (from the
    # spread of a few blocks' gradients, at a kink of the loss) covered 3 of 16 draws. The
    # interval is then the paired test's, which covers it
    lo_b, hi_b = (float(b[0]) for b in effects.ALL["torque_limit"].bounds(pend))
    hits = 0
    for seed in range(6):
        data, scale = _data(pend, {"torque_limit": 0.7}, 4, 100, 1000 + seed)
        f = fit.fit(pend, data, scale, ("torque_limit",), CFG.fit)
        x, lo, hi = f.params["torque_limit"][0], f.lo["torque_limit"][0], f.hi["torque_limit"][0]
        assert lo_b <= lo <= x <= hi <= hi_b, (seed, lo, x, hi)
        hits += lo <= 0.7 <= hi
    assert hits >= 5, hits


def test_estimate_on_a_bound_is_flagged_and_its_interval_clipped(pend):
    # a motor at 20% of its constant: torque_scale's lower bound is 0.3
    data, scale = _data(pend, {"torque_scale": 0.2}, 3, 80, 5, noise=False)
    f = fit.fit(pend, data, scale, ("torque_scale",), CFG.fit)
    assert f.params["torque_scale"][0] == pytest.approx(0.3, abs=1e-3)
    assert f.at_bound["torque_scale"].tolist() == [True]
    assert f.lo["torque_scale"][0] >= 0.3 - 1e-12 and f.hi["torque_scale"][0] >= f.params["torque_scale"][0]
    # a nominal value on a bound (no delay) is an absent effect, not a truncated one
    g = fit.fit(pend, data, scale, ("delay",), CFG.fit)
    if g.params["delay"][0] == 0:
        assert not g.at_bound["delay"].any()


def test_vector_and_pair_intervals_contain_the_estimate(pend):
    data, scale = _data(pend, {"com_offset": [0.0, 0.0, 0.05], "delay": 1}, 4, 100, 3)
    f = fit.fit(pend, data, scale, ("com_offset",), CFG.fit)
    lo, hi = effects.ALL["com_offset"].bounds(pend)
    x = f.params["com_offset"]
    assert np.all(lo <= f.lo["com_offset"]) and np.all(f.lo["com_offset"] <= x)
    assert np.all(x <= f.hi["com_offset"]) and np.all(f.hi["com_offset"] <= hi)
    # the planar pendulum cannot see the offset along its hinge axis: the interval is the bounds
    assert f.lo["com_offset"][1] == lo[1] and f.hi["com_offset"][1] == hi[1]
    assert f.lo["com_offset"][2] < 0.05 < f.hi["com_offset"][2]
    p = fit.fit(pend, data, scale, ("com_offset", "delay"), CFG.fit, {"delay": np.array([1.0])})
    for n in p.names:
        assert np.all(p.lo[n] <= p.params[n]) and np.all(p.params[n] <= p.hi[n]), (n, p.lo[n], p.params[n], p.hi[n])
    assert p.lo["delay"][0] <= 1 <= p.hi["delay"][0]


def test_unstable_worlds_are_nan_counted_and_silent(pend, capfd):
    q, qd = np.zeros((4, 1)), np.array([[0.0], [1e200], [0.5], [np.inf]])
    before = sim.unstable()
    _, v = sim.step(pend, effects.build(pend), q, qd, np.zeros((4, 1, 1)))
    after = sim.unstable()
    assert np.isnan(v[[1, 3]]).all() and np.isfinite(v[[0, 2]]).all()
    assert after["diverged"] - before["diverged"] == 2 and after["warnings"] > before["warnings"]
    assert "WARNING" not in capfd.readouterr().err
    # a fit objective scores a diverged replay as a very bad fit and counts the evaluation
    data, scale = _data(pend, {}, 2, 30, 0, noise=False)
    bad = data._replace(qd=data.qd.copy())
    bad.qd[data.start[3]] = 1e200
    obj = fit.Objective(pend, bad, scale, ("damping",))
    assert obj.losses(np.array([0.0])).sum() >= 1e6 and obj.unstable == 1


def _w(explained_above_floor, structure_left, p_value=2.5e-4, ties=False):
    best = {"effects": ["damping"], "params": {"damping": [5.0]}, "at_bound": {"damping": [True]},
            "explained": explained_above_floor, "explained_above_floor": explained_above_floor,
            "explained_ci": [explained_above_floor - 0.1, explained_above_floor + 0.1], "p_beats_next": 0.99}
    other = {"effects": ["armature"], "p_matches_best": 0.2 if ties else 0.0}
    det = {"significant": p_value < 0.005, "p_value": p_value, "p_floor": 2.5e-4, "p_normal": 1e-9,
           "level": 0.005, "hypotheses": 10, "explained_crossfit": 0.2}
    return {"ranking": [best, other], "detection": det, "probe_explained_nominal": 0.0, "gap_ms": 1.0,
            "noise_floor": 0.0, "structure_left": structure_left, "structure_hints": []}


def test_verdict_reasons_name_the_rule_and_list_ties():
    cfg = diagnose.DiagnoseConfig()
    v = attribute.verdict(_w(0.13, 0.0, ties=True), cfg)
    assert v["verdict"] == "unexplained by the library" and v["indistinguishable_from"] == ["armature"]
    assert "closes 13.0% of the held-out gap above the noise floor" in v["reason"]
    assert "below the 50% rule" in v["reason"] and "at the bound: damping = 5" in v["reason"]
    assert "sign-flip p = 0.00025 (its floor; normal approximation 1e-09)" in v["reason"]
    v = attribute.verdict(_w(0.9, 0.4), cfg)
    assert v["verdict"] == "unexplained by the library" and "above the 15% rule" in v["reason"]
    v = attribute.verdict(_w(0.9, 0.0, ties=True), cfg)
    assert v["verdict"] == "explained" and not v["confident"] and "other effects tie" in v["reason"]
    v = attribute.verdict(_w(0.9, 0.0, p_value=0.3, ties=True), cfg)
    assert v["verdict"] == "no significant gap" and v["indistinguishable_from"] == ["armature"]
    assert "needs < 0.005 = 0.05 / 10 hypotheses" in v["reason"]


def test_a_share_under_the_rule_whose_interval_reaches_it_is_named_not_confidently():
    cfg = diagnose.DiagnoseConfig()
    v = attribute.verdict(_w(0.45, 0.0), cfg)  # interval [0.35, 0.55] holds the rule's 50%
    assert v["verdict"] == "explained" and not v["confident"] and v["effects"] == ["damping"]
    assert "within reach of the 50% rule" in v["reason"] and "cannot tell it from the rule's edge" in v["reason"]
    assert "[35.0%, 55.0%]" in v["reason"]
    old = attribute.verdict(_w(0.45, 0.0), dataclasses.replace(cfg, attribute_interval=False))
    assert old["verdict"] == "unexplained by the library" and "upper bound" not in old["reason"]
    v = attribute.verdict(_w(0.39, 0.0), cfg)  # [0.29, 0.49]: under the rule, significantly
    assert v["verdict"] == "unexplained by the library"
    assert "its upper bound 49.0% of the whole gap stays below the rule's 50.0%" in v["reason"]
    # the floor moves the rule on the whole gap: 50% above a floor of 0.2 is 40% of the whole
    w = _w(0.45, 0.0)
    w["noise_floor"], w["ranking"][0]["explained_ci"] = 0.2, [0.30, 0.39]
    assert attribute.verdict(w, cfg)["verdict"] == "unexplained by the library"
    w["ranking"][0]["explained_ci"] = [0.30, 0.41]
    assert attribute.verdict(w, cfg)["verdict"] == "explained"
    # with structure left the verdict stays unexplained, and says the share was within reach
    v = attribute.verdict(_w(0.45, 0.4), cfg)
    assert v["verdict"] == "unexplained by the library" and "(its interval reaches it)" in v["reason"]
    assert v["rule"] == "structure_max"


def test_the_line_search_stops_at_a_quarter_of_the_standard_error():
    # per-block losses a_b (x - c_b)^2: the loss's curvature and its per-block gradients are
    # known, so the sandwich standard error at the best grid node is too
    rng = np.random.default_rng(0)
    nb = 60
    a, c = rng.uniform(0.5, 2.0, nb), rng.normal(0.5, 0.12, nb)
    xs = np.linspace(0.0, 1.0, 11)
    B = a[None] * (xs[:, None] - c[None]) ** 2  # [P, nb]
    k = int(np.argmin(B.sum(1)))
    obj = type("O", (), {"nxt": np.full(nb, -1)})()  # independent blocks
    g = 2 * a * (xs[k] - c)
    se = np.sqrt(((g - g.mean()) ** 2).sum() * nb / (nb - 1)) / (2 * a.sum())
    tol = fit.line_tol(obj, xs, B, k, 1.0)
    assert fit.LINE_SE == 0.25 and 1e-4 < tol < 1e-2 and tol == pytest.approx(0.25 * se, rel=1e-9)
    # a tiny spread: the floor; a huge one: the ceiling; the grid's edge or a concave loss: the floor
    assert fit.line_tol(obj, xs, a[None] * (xs[:, None] - 0.5) ** 2 + 1e-9 * B, k, 1.0) == 1e-4
    a2, d = np.tile(a[:nb // 2], 2), np.concatenate([c[:nb // 2] - 0.5, 0.5 - c[:nb // 2]]) * 100
    wide = a2[None] * (xs[:, None] - 0.5 - d[None]) ** 2  # optimum 0.5, blocks wildly apart
    assert fit.line_tol(obj, xs, wide, int(np.argmin(wide.sum(1))), 1.0) == 1e-2
    assert fit.line_tol(obj, xs, B, 0, 1.0) == 1e-4 and fit.line_tol(obj, xs, -B, k, 1.0) == 1e-4


def test_the_parabolic_line_search_finds_the_minimum_within_its_tolerance_in_few_evaluations():
    xs = np.linspace(0.0, 1.0, 9)

    def search(f, tol=1e-4):
        L = np.array([f(x) for x in xs])
        k = int(np.argmin(L))
        calls = []
        x, fx, n = fit.line_search(lambda v: calls.append(v) or f(v), dict(zip(xs, L)),
                                   xs[max(k - 1, 0)], xs[min(k + 1, 8)], tol)
        assert n == len(calls) and fx == pytest.approx(f(x)) and fx <= L.min()
        return x, n

    x, n = search(lambda v: 3 * (v - 0.3141) ** 2 + 1)  # a quadratic: its vertex at once, then a confirmation
    assert x == pytest.approx(0.3141, abs=1e-12) and n == 2
    rng = np.random.default_rng(1)
    worst = []
    for _ in range(40):  # convex, skewed, not quadratic: within a few tolerances of the minimum c
        c, w = rng.uniform(0.05, 0.95), rng.uniform(1, 12)
        x, n = search(lambda v: np.exp(w * (v - c)) - w * (v - c))
        assert abs(x - c) < 3e-4 and n <= 10, (c, w, x, n)
        worst.append(n)
    ref = [optimize.minimize_scalar(lambda v: np.exp(w * (v - c)) - w * (v - c), bounds=(c - 0.125, c + 0.125),
                                    method="bounded", options={"xatol": 1e-4}).nfev for c, w in ((0.4, 3), (0.6, 9))]
    assert np.mean(worst) < min(ref), (np.mean(worst), ref)  # fewer than Brent's bounded search
    x, n = search(lambda v: (v + 0.2) ** 2)  # the minimum beyond the lower bound: the bound, two
    assert x == 0.0 and n == 2  # replays (a golden step into the edge cell, then one tol inward)
    # the minimum inside the edge cell, on a loss whose roughness hides the slope at one tol from
    # the bound (f(tol) > f(0)): the probe into the cell finds it
    rough = lambda v: 10 * (v - 0.05) ** 2 + 1e-3 * np.sin(2e4 * v)
    assert rough(1e-4) > rough(0.0)
    x, n = search(rough)
    assert abs(x - 0.05) < 0.02 and rough(x) < rough(0.0) - 0.02 and n <= 25, (x, n)
    x, n = search(lambda v: (v - 0.99) ** 2 + 0.5 * abs(v - 0.99))  # kinked near the upper bound
    assert abs(x - 0.99) < 1e-3, x
    x, n = search(lambda v: -np.cos(40 * v) - v)  # rough: still the best evaluated point, at most 25 steps
    assert n <= 25


def test_a_scalar_fit_ends_at_its_own_standard_error_not_the_grids(pend):
    """On noise-free logs the k-step replay at the planted value is exact, so the fit must land
    on it: the grid's tolerance (read where the grid's nodes are far from the minimum) stopped the
    search at 0.3042 for 0.3, outside the interval's 0.0002 half width; a second search with the
    tolerance read at the first one's end lands within 0.0005, and the interval covers 0.3."""
    data, scale = _data(pend, {"damping": 0.3}, 8, 150, 1000, noise=False)
    f = fit.fit(pend, data, scale, ("damping",), CFG.fit)
    x, lo, hi = f.params["damping"][0], f.lo["damping"][0], f.hi["damping"][0]
    assert abs(x - 0.3) < 5e-4 and lo <= 0.3 <= hi, (lo, x, hi)


def test_a_fit_replays_no_parameter_vector_twice(pend, monkeypatch):
    # the least squares' start and end and the interval's centre are asked for again: one replay each
    data, scale = _data(pend, {"com_offset": [0.0, 0.0, 0.05]}, 3, 80, 4)
    replayed = []
    one = fit.residual
    monkeypatch.setattr(fit, "residual", lambda sm, plan, *a: replayed.append(plan) or one(sm, plan, *a))
    f = fit.fit(pend, data, scale, ("com_offset",), CFG.fit)
    keys = [(p.mj.body_ipos.tobytes(), p.mj.body_mass.tobytes()) for p in replayed]
    assert len(keys) == len(set(keys)) and len(keys) < f.evals, (len(keys), len(set(keys)), f.evals)
    obj = fit.Objective(pend, data, scale, ("damping",))
    r = obj.residual(np.array([0.2]))
    n = len(replayed)
    assert np.array_equal(obj.residual(np.array([0.2])), r) and len(replayed) == n and obj.evals == 2


def test_an_objectives_own_cache_keeps_its_most_recent_residuals():
    c = fit._Recent(3)
    for i in range(5):
        c[i] = i
    c.update({5: 5})
    assert list(c) == [3, 4, 5]
    c[3] = 30  # written again: the most recent
    c.update({6: 6})
    assert list(c) == [5, 3, 6] and c[3] == 30


class _Rough:
    """A two-parameter least-squares objective, quadratic with a bump of 1e-6 x its loss every
    1e-5 of the range (the rough contact loss of a legged robot at tiny steps)."""

    def __init__(self):
        self.evals = 0

    def residual(self, p):
        self.evals += 1
        p = np.asarray(p, float)
        return np.concatenate([p - np.array([0.3, 0.7]), [1e-3 * np.sin(1e5 * p.sum())]])

    def losses(self, p):
        return np.array([(self.residual(p) ** 2).sum()])


def test_a_pair_fit_stops_once_its_steps_are_below_a_thousandth_of_the_ranges(monkeypatch):
    cfg, lo, hi = fit.FitConfig(max_nfev=20), np.zeros(2), np.ones(2)
    got, ours = {}, fit.XTOL
    for xtol in (ours, 1e-8):
        monkeypatch.setattr(fit, "XTOL", xtol)
        obj = _Rough()
        x, _ = fit.fit_vector(obj, cfg, np.array([0.9, 0.1]), lo, hi)
        got[xtol] = (x, obj.evals)
    (x, n), (x8, n8) = got[ours], got[1e-8]
    assert np.abs(x - [0.3, 0.7]).max() < 2e-3 and np.abs(x8 - [0.3, 0.7]).max() < 2e-3
    assert n < n8, (n, n8)  # SciPy's default tolerance keeps shrinking its trust region on the bumps


def test_a_single_far_behind_keeps_its_grid_node(pend):
    data, scale = _data(pend, {"damping": 0.3}, 3, 80, 5, noise=False)
    full = fit.fit(pend, data, scale, ("damping",), CFG.fit, interval=False)
    left = fit.fit(pend, data, scale, ("damping",), CFG.fit, interval=False, grid_only_above=0.0)
    lo, hi = (float(b[0]) for b in effects.ALL["damping"].bounds(pend))
    grid = np.linspace(lo, hi, CFG.fit.grid)
    assert left.grid_only and not full.grid_only and left.evals < full.evals
    assert np.min(np.abs(grid - left.params["damping"][0])) < 1e-12 or left.params["damping"][0] == 0.0
    assert full.train_loss <= left.train_loss
    # an effect with a better grid node than the bar is searched as before
    again = fit.fit(pend, data, scale, ("damping",), CFG.fit, interval=False, grid_only_above=1e300)
    assert not again.grid_only and again.params["damping"][0] == full.params["damping"][0]
