"""Calibration of the simulator's own settings, fitted first, as the baseline that physical effects
are scored against.

A real robot differs from any simulator in ways that are no physical effect: the simulator's
friction cone, contact model (solref, solimp, margin, impratio), which geoms collide, time step
and integrator. Left in the nominal model, such a model-form difference dominates the gap and
library effects get pulled in to imitate it (a softer contact, a payload). So the diagnosis first
fits these settings (:class:`stride_jax.gap.nominal.Settings`) as nuisance parameters on the
training split, keeps them only where they lower the held-out gap, and then fits the physical
effects on top of the calibrated model (the *baseline*). Both are reported apart: "the
simulator's contact model is off by ..., and on top of that ...".

Search (k-step replay loss on the training split, every ``subsample``-th replay, thinned further
to at most ``windows`` replays: a dozen settings need far fewer replays than the physical effects'
fits, and a replay of the shipped Go1 costs ~6x the MJX-training form's):

1. start: the nominal model, and the robot's MJX-training form where it has one
   (:func:`stride_jax.gap.nominal.training_settings`), whichever has the lower loss;
2. discrete settings (time step, integrator, cone, collision set, foot contact dimension) by
   coordinate descent: every value of one setting with the others fixed, kept if it lowers the
   loss by more than ``min_gain`` (relative; a finer time step by ``min_gain`` times the factor by
   which it multiplies the replays' cost, ``step_cost``), ``sweeps`` passes;
3. continuous settings (solref time constant and damping ratio, solimp softness and width,
   margin, impratio) jointly by box-constrained least squares in coordinates normalised to their
   (log) ranges, with 2%-of-range finite-difference steps replayed in one batch, at most
   ``max_nfev`` iterations per setting; then each is put back to its neutral
   value where that costs less than ``min_gain`` of the loss (only settings that matter are
   reported);
3b. 2 and 3 in turns, at most ``rounds`` times: the discrete settings swept again at the fitted
   continuous ones, and the continuous refitted where a discrete one moved (:func:`in_turns`);
3c. a second start (``continuous_first``): the continuous settings fitted first at the nominal
   model's own discrete settings, then 2-3b from there; the lower training loss of the two
   searches is kept (record ``search``). The discrete sweep at the nominal contact parameters can
   pick a cone or contact dimension that only those parameters favour, and the later turns start
   from the continuous fit made for it: on four no-effect Go1 controls whose calibration left a
   gap, the search ended 190-120000x above the training loss of the drawn settings, and the
   second start came to within 8x of it or below (``results/gap_calibration_starts.log``).
4. held-out: the calibrated baseline is kept only if it lowers the held-out k-step gap
   (otherwise the nominal model stays the baseline, and the report says so), with a one-sided
   sign-flip test of the paired block improvements reported beside it.
5. once the effects are ranked on that baseline (:mod:`stride_jax.gap.diagnose`), the search
   again with the best hypothesis held fixed where the refinement held another effect
   (:func:`recheck`), adopted where it predicts the held-out split materially and significantly
   better; the effects are then scored again on it.

What calibration can and cannot tell apart is in ``docs/gap.md``: a softer ground and a longer
solref time constant are the same dynamics (the library's ``contact_softness`` is that knob), and
contact parameters can take up part of a payload or of ground friction. How the baseline is
scored and described (its residual and gaps, the verdict's clause) is
:mod:`stride_jax.gap.baseline`'s.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any

import numpy as np
from scipy import optimize

from stride_jax.gap import effects, finer, fit, nominal, replay
from stride_jax.gap.baseline import residual
from stride_jax.gap.nominal import CONTINUOUS, Settings
from stride_jax.sim.model import SimModel

DISCRETE = ("timestep", "integrator", "cone", "contacts", "foot_condim")
MODES = ("fit", "off")


@dataclasses.dataclass(frozen=True)
class CalibrateConfig:
    """Calibration of the simulator's settings before the physical effects.

    Attributes:
      mode: ``fit`` (calibrate, then score effects on the calibrated baseline) or ``off`` (the
        nominal model is the baseline).
      discrete: comma-separated discrete settings to search (timestep, integrator, cone,
        contacts, foot_condim).
      continuous: comma-separated continuous settings to fit (solref_timeconst,
        solref_dampratio, solimp_softness, solimp_d0, solimp_dmax, solimp_width, margin,
        impratio); empty: none. By default solimp's d0 and dmax move together
        (``solimp_softness``): apart, dmax took x 2.22 on the independent Go1 benchmark's noisy
        delay case where the "real" contact was the model's own, and the time step and delay
        moved with it (delay + inertia@thigh named instead of delay).
      integrators: comma-separated integrators to try (``euler_nodamp``: Euler without
        implicit damping).
      timestep_min, timestep_max: time steps tried (s; those in range that divide the control
        period, at 0.5 ms resolution, and the model's own).
      sweeps: coordinate-descent passes over the discrete settings (per round).
      rounds: turns of discrete sweeps and continuous fit (a discrete setting that moves once the
        continuous ones are fitted has them refitted; 1: discrete first, continuous once).
      max_nfev: least-squares iterations per continuous setting (each one evaluation plus a
        batched finite-difference Jacobian of one per setting; fewer once converged).
      subsample: fit on every n-th replayed sample of the training split (the held-out check
        uses all).
      windows: ... and on at most this many of them (a larger stride where the training split
        has more; 0: no cap).
      min_gain: relative loss decrease a setting must bring to be changed (discrete) or kept
        (continuous).
      step_cost: a finer time step must bring ``min_gain`` times the factor by which it multiplies
        the cost of every later replay (2 ms -> 1 ms: 2%): on the shipped Go1 a 1 ms step won
        1.4% of the training loss and doubled the calibration's and the effect screen's replays
        (~60 s of a 5-minute diagnosis; ``experiments/probes/calibration_time.py``). Off: every
        time step needs ``min_gain`` alone.
      block: control steps per block of the held-out sign-flip test.
      seed: of the sign flips.
      screen_steps: Gauss-Newton steps per effect in the screen of :func:`refine` (the first
        from a secant replay, the others a parabola's vertex for the four best effects).
      refine_finer: that screen also takes the joint groups (:func:`stride_jax.gap.finer.children`:
        per joint type, leg, side and end) of this many of its best joint effects, so the
        refinement can hold ``damping@calf`` where the logs carry it rather than ``damping`` on
        every joint (0: the library's effects only).
      refine_finer_margin: a group is held only where its training loss is at most
        ``1 - refine_finer_margin`` of the best library effect's (the ranking's finer rule,
        ``ScreenConfig.finer_margin``; the independent benchmark's torque limit 0.4: kp_scale@rear
        1.8% below torque_scale, its CoM offset: torque_limit@front 8.1% below payload; no
        group's signature). :func:`held_choice`.
      refine: screen the scalar library effects on top of the first calibration (:func:`screen`),
        and fit the settings again with the best of them held fixed on top (a strong physical
        effect biases settings fitted without it: a planted damping pulled the Go1's integrator
        to RK4); and screen the contact effects that no setting reproduces (ground friction) on
        the nominal model, calibrating again from the start with the best held fixed, adopted
        where it fits better held out (:func:`_contact_effect_start`).
      second_start: the share of the nominal model's training loss that contact effect must close
        on its own for that second start (1 or more: never).
      recheck: once the diagnosis has its best hypothesis, fit the settings again with it held
        fixed on top where it differs from the effect the refinement held (:func:`recheck`), and
        score the effects again on them where they predict the held-out split better: by at
        least ``recheck_min`` of its gap, significantly (one-sided sign-flip test over held-out
        blocks at ``recheck_p``).
      continuous_first: also search from the continuous settings fitted first (step 3c), keeping
        the lower training loss (one more search: 16-28 s on the shipped Go1's 6 x 4 s logs, ~33 s
        on 12 x 8 s; only in a first pass, not in a pass started from its settings).
    """

    mode: str = "fit"
    discrete: str = "timestep,integrator,cone,contacts,foot_condim"
    continuous: str = "solref_timeconst,solref_dampratio,solimp_softness,solimp_width,margin,impratio"
    integrators: str = "euler,euler_nodamp,implicitfast,rk4"
    timestep_min: float = 0.0009
    timestep_max: float = 0.0101
    sweeps: int = 2
    rounds: int = 2
    max_nfev: int = 4
    subsample: int = 2
    windows: int = 400
    min_gain: float = 0.01
    step_cost: bool = True
    block: int = 10
    seed: int = 0
    screen_steps: int = 3
    refine_finer: int = 2
    refine_finer_margin: float = 0.1
    refine: bool = True
    second_start: float = 0.5
    recheck: bool = True
    recheck_min: float = 0.1
    recheck_p: float = 0.05
    continuous_first: bool = True

    def __post_init__(self):
        if self.mode not in MODES:
            raise ValueError(f"calibrate.mode {self.mode!r} is not one of {', '.join(MODES)}")
        bad = [n for n in _names(self.discrete) if n not in DISCRETE]
        bad += [n for n in _names(self.continuous) if n not in CONTINUOUS]
        bad += [n for n in _names(self.integrators) if n not in nominal.INTEGRATORS]
        if bad:
            raise ValueError(f"calibrate: unknown setting(s) {bad}; discrete: {', '.join(DISCRETE)}; continuous: "
                             f"{', '.join(CONTINUOUS)}; integrators: {', '.join(nominal.INTEGRATORS)}")
        if self.sweeps < 1 or self.rounds < 1 or self.max_nfev < 1 or self.subsample < 1 or self.block < 1:
            raise ValueError("calibrate: sweeps, rounds, max_nfev, subsample and block must be >= 1")
        if self.windows < 0:
            raise ValueError(f"calibrate.windows {self.windows} must be >= 0 (0: no cap)")
        if not 0 < self.timestep_min <= self.timestep_max:
            raise ValueError(f"calibrate: timestep range [{self.timestep_min}, {self.timestep_max}] is empty")
        if self.refine_finer < 0 or not 0 <= self.refine_finer_margin < 1:
            raise ValueError(f"calibrate.refine_finer {self.refine_finer} must be >= 0 (0: no joint groups) and "
                             f"refine_finer_margin {self.refine_finer_margin} in [0, 1)")
        if self.min_gain < 0:
            raise ValueError(f"calibrate.min_gain {self.min_gain} must be >= 0")
        if not (0 <= self.recheck_min < 1 and 0 < self.recheck_p <= 1):
            raise ValueError(f"calibrate: recheck_min {self.recheck_min} must be in [0, 1) and recheck_p "
                             f"{self.recheck_p} in (0, 1]")
        if not self.second_start >= 0:
            raise ValueError(f"calibrate.second_start {self.second_start} must be >= 0 (1 or more: no second start)")


def _names(s: str) -> list[str]:
    return [x.strip() for x in s.split(",") if x.strip()]


@dataclasses.dataclass(frozen=True)
class Calibration:
    """The baseline model (``model``: the nominal one with ``settings``), and the JSON-able
    ``record`` of the search and the held-out check; ``heldout``: the held-out residuals computed
    on the way, by (settings, effects held fixed), which :func:`refine` reuses."""

    model: SimModel
    settings: Settings
    record: dict
    heldout: dict = dataclasses.field(default_factory=dict, repr=False, compare=False)


FTOL = 1e-3  # least squares stops when a step lowers the loss by less than 0.1% (min_gain is 1%)


def stride(cfg: CalibrateConfig, n: int) -> int:
    """The stride over ``n`` training replays: ``cfg.subsample``, larger where that leaves more
    than ``cfg.windows``."""
    return fit.capped_stride(cfg.subsample, n, cfg.windows)


def _sub(data: fit.Data, n: int) -> fit.Data:
    """Every ``n``-th replay of ``data``."""
    if n <= 1:
        return data
    keep = np.arange(len(data.start)) % n == 0
    return data._replace(start=data.start[keep], first=data.first[keep], target=data.target[keep],
                         traj=data.traj[keep])


def _pick(trial: list[Settings], name: str, loss, tol: float, own) -> Settings:
    """The best of ``trial`` (settings differing in ``name``), preferring among those within
    ``tol`` of the lowest loss the nominal model's own value ``own``, else the cheapest: the
    largest time step, else the lowest loss."""
    L = min(loss(s) for s in trial)
    near = [s for s in trial if loss(s) <= L * (1 + tol)]
    mine = [s for s in near if getattr(s, name) == own]
    if mine:
        return mine[0]
    if name == "timestep":
        return max(near, key=lambda s: s.timestep)
    return min(near, key=loss)


def _neutral(s: Settings, own: dict) -> Settings:
    """``s`` with every discrete field that equals the nominal model's own value set to None."""
    same = {n: None for n in DISCRETE + ("iterations",) if getattr(s, n) is not None and getattr(s, n) == own.get(n)}
    if s.timestep is not None and abs(s.timestep - own["timestep"]) < 1e-12:
        same["timestep"] = None
    return dataclasses.replace(s, **same)


class ByModel(dict):
    """Training losses keyed by the model a :class:`Settings` makes: settings that differ only in
    naming the nominal model's own discrete value (``iterations=100`` against ``None`` on a model
    whose cap is 100) are one key (:func:`_neutral`), so that no model is replayed twice. Before,
    the Go1's calibration replayed 11-13 of its 71 models twice per pass (a sweep repeated because
    the solver cap "moved" from None to its own value, and the calibrated settings re-scored in
    their neutral form)."""

    def __init__(self, own: dict):
        super().__init__()
        self.own = own

    def __contains__(self, s) -> bool:
        return super().__contains__(_neutral(s, self.own))

    def __getitem__(self, s) -> float:
        return super().__getitem__(_neutral(s, self.own))

    def __setitem__(self, s, value) -> None:
        super().__setitem__(_neutral(s, self.own), value)

    def get(self, s, default=None):
        return super().get(_neutral(s, self.own), default)


def parsimony(s: Settings, L: float, names: list[str], loss, min_gain: float) -> tuple[Settings, float]:
    """``s`` (training loss ``L``) with each continuous setting of ``names`` put back to neutral
    where that costs less than ``min_gain`` of the loss, nearest to neutral first: a least-squares
    optimum keeps every setting a little off neutral (a contact margin of microns that no
    real contact model has, but which moves replays across the contact threshold)."""
    for n in sorted(names, key=lambda n: abs(_z(n, getattr(s, n)) - _z(n, CONTINUOUS[n][3]))):
        trial = dataclasses.replace(s, **{n: CONTINUOUS[n][3]})
        if trial != s and (L_trial := loss(trial)) <= L * (1 + min_gain):
            s, L = trial, L_trial
    return s, L


def _signflip(d: np.ndarray, n: int, seed: int) -> float:
    flips = np.random.default_rng(seed).choice([-1.0, 1.0], size=(n, len(d)))
    return float((1 + ((flips @ d) >= d.sum() - 1e-12 * np.abs(d).sum()).sum()) / (1 + n))


def paired_p(r_before: np.ndarray, r_after: np.ndarray, test: fit.Data, block: int, seed: int) -> float:
    """One-sided sign-flip p that ``r_after`` (``[M, nv]`` residuals on ``test``) fits better than
    ``r_before``: the paired differences of their squared residuals summed over blocks of
    ``block`` control steps (:func:`stride_jax.gap.fit.block_ids`), 4000 flips."""
    ids, nb, _ = fit.block_ids(test, block)
    bl = lambda r: np.bincount(ids, weights=(r ** 2).sum(1), minlength=nb)
    return _signflip(bl(r_before) - bl(r_after), 4000, seed)


def _heldout_key(s: Settings, applied: dict | None) -> tuple:
    """The key of :attr:`Calibration.heldout`: the settings and the effects held fixed on top."""
    return s, tuple(sorted((n, tuple(np.atleast_1d(v).tolist())) for n, v in (applied or {}).items()))


def _z(name: str, v: float) -> float:
    """Setting ``name``'s value ``v`` in coordinates normalised to its (log) range: 0 at the low
    bound, 1 at the high one."""
    lo, hi, log = CONTINUOUS[name][:3]
    f = np.log if log else (lambda x: x)
    return float((f(v) - f(lo)) / (f(hi) - f(lo)))


def _from_z(name: str, z: float) -> float:
    lo, hi, log = CONTINUOUS[name][:3]
    z = min(max(float(z), 0.0), 1.0)
    v = float(np.exp(np.log(lo) + z * (np.log(hi) - np.log(lo)))) if log else lo + z * (hi - lo)
    return CONTINUOUS[name][3] if abs(v - CONTINUOUS[name][3]) < 1e-9 else v


def fit_continuous(sm: SimModel, start: Settings, data: fit.Data, scale: np.ndarray, names: list[str],
                   max_nfev: int, applied: dict | None = None, cache: dict | None = None,
                   evals: dict | None = None) -> tuple[Settings, float, np.ndarray]:
    """The continuous settings ``names`` fitted jointly from ``start`` (the others as ``start`` has
    them) by box-constrained least squares of the ``k``-step residual on ``data``, in coordinates
    normalised to each setting's (log) range; ``applied``: library effects held fixed on top.

    The Jacobian is a forward difference with 2%-of-range steps (backward at the upper bound),
    its ``len(names)`` models replayed in one batch (:mod:`stride_jax.gap.replay`). At most
    ``max_nfev * len(names)`` iterations (each one step and, once the step is taken, one
    Jacobian), fewer where a step lowers the loss by less than :data:`FTOL`: a budget that
    counted the Jacobian's replays too left the contact settings unconverged (the re-fit of
    ``tests/test_gap_admit.py`` missed). Returns ``(settings, loss, z)``:
    ``start`` itself where the fit does not lower its loss."""
    cache = {} if cache is None else cache
    evals = {"n": 0} if evals is None else evals
    names = list(names)
    n, h = len(names), 0.02
    iters = max_nfev * n
    budget = 1 + iters * (n + 1)  # replays: the start, then one step and one Jacobian per iteration
    used = {"n": 0, "J": None}
    base = nominal.apply(sm, start)  # every point shares its time step (and so the substep count)
    held = {m: np.atleast_1d(np.asarray(v, float)) for m, v in (applied or {}).items()}

    def settings_at(z):
        return dataclasses.replace(start, **{m: _from_z(m, v) for m, v in zip(names, z)})

    def resids(Z) -> list[np.ndarray]:
        ss = [settings_at(z) for z in Z]
        plans = [effects.build(nominal.apply(sm, s), held) for s in ss]
        R = replay.residuals(base, plans, data, scale)
        evals["n"] += len(ss)
        used["n"] += len(ss)
        for s, r in zip(ss, R, strict=True):
            cache[s] = float((r ** 2).sum())
        return list(R)

    seen: dict[bytes, np.ndarray] = {}

    def fun(z):
        key = np.asarray(z, float).tobytes()
        if key not in seen:
            seen[key] = resids([z])[0].ravel()
        return seen[key]

    def jac(z):
        z = np.asarray(z, float)
        if used["J"] is not None and used["n"] + n > budget:
            return used["J"]  # out of budget: the fit stops after this iteration anyway
        steps = np.where(z + h <= 1.0, h, -h)
        R = resids([z + steps[i] * np.eye(n)[i] for i in range(n)])
        f = fun(z)
        used["J"] = np.stack([(r.ravel() - f) / steps[i] for i, r in enumerate(R)], axis=1)
        return used["J"]

    z0 = np.array([_z(m, getattr(start, m)) for m in names]).clip(0, 1)
    s0 = settings_at(z0)  # ``start`` through the normalised coordinates: equal up to rounding (or clipped)
    if s0 not in cache:
        fun(z0)
    L0 = cache[s0]
    res = optimize.least_squares(fun, z0, jac=jac, bounds=(0, 1), method="trf", max_nfev=iters + 1, x_scale=1.0,
                                 ftol=FTOL, xtol=FTOL)
    if 2 * res.cost < L0:
        s = settings_at(res.x)
        return s, cache.get(s, float(2 * res.cost)), res.x
    return start, L0, z0


def _sweep(best: Settings, values: dict, own: dict, loss, cfg: CalibrateConfig, path: list, round_: int
           ) -> tuple[Settings, bool]:
    """Coordinate descent over the discrete settings from ``best`` (at most ``cfg.sweeps`` passes;
    a change must lower the loss by ``min_gain``, or return to the model's own value at no more
    than that cost); appends each move to ``path``. Returns ``(settings, moved)``."""
    moved_any = False
    for _ in range(cfg.sweeps):
        moved = False
        for name in _names(cfg.discrete) + ["iterations"]:
            cur = loss(best)
            trial = [dataclasses.replace(best, **{name: v}) for v in values[name]]
            if name == "timestep" and cfg.step_cost:  # a finer step pays for the replays it multiplies
                trial = [s for s in trial if s.timestep >= best.timestep
                         or loss(s) < (1 - cfg.min_gain * best.timestep / s.timestep) * cur]
            if not trial:
                continue
            cand = _pick(trial, name, loss, cfg.min_gain, own.get(name))
            back = getattr(cand, name) == own.get(name) and loss(cand) <= (1 + cfg.min_gain) * cur
            # a move changes the model (not None -> the model's own value, :class:`ByModel`)
            if _neutral(cand, own) != _neutral(best, own) and (loss(cand) < (1 - cfg.min_gain) * cur or back):
                path.append({"setting": name, "value": getattr(cand, name), "loss": loss(cand), "from": cur,
                             "round": round_})
                best, moved = cand, True
        moved_any |= moved
        if not moved:
            break
    return best, moved_any


def _ties(best: Settings, values: dict, loss, cfg: CalibrateConfig) -> dict[str, list]:
    """Discrete values the training loss cannot tell apart from ``best``'s (within ``min_gain``)."""
    ties = {}
    for name in _names(cfg.discrete):
        L_best = loss(best)
        alt = [v for v in values[name] if v != getattr(best, name)
               and loss(dataclasses.replace(best, **{name: v})) <= L_best * (1 + cfg.min_gain)]
        if alt:
            ties[name] = alt
    return ties


def in_turns(best: Settings, values: dict, own: dict, loss, fit_cont, cont: list[str], cfg: CalibrateConfig,
             path: list) -> tuple[Settings, dict[str, list], dict[str, Any]]:
    """Steps 2, 3 and 3b of the module docstring: the discrete settings by coordinate descent
    (:func:`_sweep` over ``values``), then the continuous ones ``cont`` (``fit_cont(settings) ->
    (settings, loss)``, then :func:`parsimony`), in turns, at most ``cfg.rounds`` times: a
    discrete value picked while the contact parameters are still the model's can be the wrong one
    once they are fitted (independent Go1 benchmark, case 10: condim 3 picked before the contact
    parameters). Stops early when a round's sweep moves nothing. ``loss(settings)``: the training
    loss. Returns ``(settings, discrete ties, continuous record)``; appends the moves to ``path``."""
    ties: dict[str, list] = {}
    cont_fit: dict[str, Any] = {}
    for round_ in range(cfg.rounds):
        best, moved_any = _sweep(best, values, own, loss, cfg, path, round_)
        if round_ and not moved_any:
            break
        # discrete values the training loss cannot tell apart from the chosen ones (within min_gain)
        ties = _ties(best, values, loss, cfg)
        if not cont:
            break
        L0 = loss(best)
        s_fit, L_fit = fit_cont(best)
        if L_fit < (1 - cfg.min_gain) * L0:
            best, L_fit = parsimony(s_fit, L_fit, cont, loss, cfg.min_gain)
        else:
            L_fit = L0
        cont_fit = {"start_loss": cont_fit.get("start_loss", L0), "fitted_loss": L_fit,
                    "kept": {n: getattr(best, n) for n in cont}, "rounds": round_ + 1}
    return best, ties, cont_fit


def two_starts(start: Settings, nominal_discrete: Settings, values: dict, own: dict, loss, fit_cont,
               cont: list[str], cfg: CalibrateConfig) -> tuple[Settings, dict, dict, list, str]:
    """Steps 2-3c of the module docstring: :func:`in_turns` from ``start`` and, with
    ``cfg.continuous_first``, again from the continuous settings ``cont`` fitted first at
    ``nominal_discrete`` (the nominal model's own discrete settings); the lower training loss
    wins. Returns ``(settings, discrete ties, continuous record, discrete path, search)``,
    ``search`` naming the start that won (``discrete first``, ``continuous first``)."""
    path: list[dict] = []
    best, ties, cont_fit = in_turns(start, values, own, loss, fit_cont, cont, cfg, path)
    out = (best, ties, cont_fit, path, "discrete first")
    if cont and cfg.continuous_first:
        path2: list[dict] = []
        best2, ties2, cont_fit2 = in_turns(fit_cont(nominal_discrete)[0], values, own, loss, fit_cont, cont, cfg,
                                           path2)
        if loss(best2) < loss(best):
            out = (best2, ties2, cont_fit2, path2, "continuous first")
    return out


def calibrate(sm: SimModel, train: fit.Data, test: fit.Data, scale: np.ndarray, cfg: CalibrateConfig,
              log=print, applied: dict | None = None, start: Settings | None = None,
              heldout: dict | None = None) -> Calibration:
    """Fits the simulator's settings on ``train`` (k-step replays), checks them on ``test``; returns
    the baseline (the nominal ``sm`` where calibration does not lower the held-out gap).

    ``applied``: library effects (name -> parameters) held fixed on top while the settings are
    fitted (the refinement pass, with the best hypothesis of a first pass); ``start``: settings
    to start the search from as well (the first pass's); ``heldout``: held-out residuals already
    computed (:attr:`Calibration.heldout` of a first pass on the same ``test``)."""
    t0 = time.time()
    heldout = {} if heldout is None else heldout

    def r_test(s: Settings, app: dict | None = None) -> np.ndarray:
        key = _heldout_key(s, app)
        if key not in heldout:
            heldout[key] = residual(sm if s == Settings() else nominal.apply(sm, s), test, scale, app)
        return heldout[key]

    sub = _sub(train, stride(cfg, len(train.start)))
    own = nominal.describe(sm)
    cache = ByModel(own)
    evals = {"n": 0}

    def loss(s: Settings) -> float:
        if s not in cache:
            evals["n"] += 1
            cache[s] = float((residual(nominal.apply(sm, s), sub, scale, applied) ** 2).sum())
        return cache[s]

    L_nom = loss(Settings())
    forms = {"shipped" if nominal.has_training_edit(sm.robot.name) else "nominal": Settings()}
    if nominal.has_training_edit(sm.robot.name):
        try:
            forms["training"] = nominal.training_settings(sm, nominal.load(sm.robot.name, "training"))
        except Exception as err:  # a robot whose training form is not expressible as settings
            log(f"  calibration: the training form is not a settings change of the nominal model ({err})")
    if start is not None and start not in forms.values():
        forms["first pass"] = start
    best = min(forms.values(), key=loss)
    # discrete: coordinate descent
    contacts = own["colliding_geoms"] > 0
    values = {"timestep": nominal.timesteps(sm, cfg.timestep_min, cfg.timestep_max),
              "integrator": _names(cfg.integrators), "cone": list(nominal.CONES) if contacts else [],
              "contacts": list(nominal.CONTACTS) if sm.nfeet else [],
              "foot_condim": [3, 6] if sm.nfeet else [],
              # the solver cap: only the training form's, where it has one (in ties the model's own)
              "iterations": sorted({s.iterations for s in forms.values() if s.iterations is not None})}
    values["timestep"] = [v for v in values["timestep"] if abs(v * 2e3 - round(v * 2e3)) < 1e-6]  # 0.5 ms multiples
    for name in values:  # the nominal model's own value is always a candidate
        if values[name] and own.get(name) is not None and own[name] not in values[name]:
            values[name].append(own[name])
    best = dataclasses.replace(best, **{n: own[n] for n in DISCRETE if getattr(best, n) is None and own.get(n) is not None})
    cont = _names(cfg.continuous) if contacts else []  # nothing collides: contact parameters change nothing
    fit_cont = lambda s: fit_continuous(sm, s, sub, scale, cont, cfg.max_nfev, applied, cache, evals)[:2]
    nominal_discrete = dataclasses.replace(Settings(), **{n: own[n] for n in DISCRETE if own.get(n) is not None})
    # a later pass (``start``: the first pass's settings, which came from the better of the two
    # starts) searches from there alone: its second start would repeat the first pass's (+33 s of
    # a 5-minute Go1 diagnosis, results/gap_speed.md)
    once = dataclasses.replace(cfg, continuous_first=False) if start is not None else cfg
    best, ties, cont_fit, path, search = two_starts(best, nominal_discrete, values, own, loss, fit_cont, cont, once)
    # held-out check
    base = nominal.apply(sm, best)
    best = _neutral(best, own)
    # held-out check: with the effects held fixed on top where given (they decide), and the
    # settings' own share without them (what the report quotes)
    r_nom, r_cal = r_test(Settings()), r_test(best)
    if applied:
        g_nom_a, g_cal_a = fit.gap(r_test(Settings(), applied)), fit.gap(r_test(best, applied))
    g_nom, g_cal = fit.gap(r_nom), fit.gap(r_cal)
    ok = bool(best != Settings() and (g_cal_a < g_nom_a if applied else g_cal < g_nom))
    p = paired_p(r_nom, r_cal, test, cfg.block, cfg.seed + 11) if best != Settings() else 1.0
    forms_heldout = {}
    for name, s in forms.items():
        forms_heldout[name] = fit.gap(r_test(s))
    record = {
        "mode": cfg.mode, "applied": ok, "effects_held_fixed": {n: np.atleast_1d(v).tolist() for n, v in (applied or {}).items()},
        "settings": {f.name: getattr(best, f.name) for f in dataclasses.fields(best)},
        "changed": nominal.summary(best, sm) if ok else [],
        "proposed": nominal.summary(best, sm),
        "nominal_settings": nominal.describe(sm),
        "train_loss_nominal": L_nom, "train_loss_calibrated": loss(best),
        "heldout_gap_nominal": g_nom, "heldout_gap_calibrated": g_cal if ok else g_nom,
        "heldout_gap_proposed": g_cal,
        # with the effects held fixed applied, of the model returned (where any were held)
        "heldout_gap_with_held": (g_cal_a if ok else g_nom_a) if applied else None,
        "shrink": (1 - g_cal / max(g_nom, 1e-300)) if ok else 0.0,
        "p_value": p, "forms_heldout": forms_heldout,
        "start": next(n for n, s in forms.items() if s == min(forms.values(), key=loss)),
        "search": search, "discrete_path": path, "discrete_ties": ties, "continuous": cont_fit,
        "evaluations": evals["n"],
        "seconds": time.time() - t0, "k": int(test.k),
    }
    if ok:
        log(f"  calibration ({evals['n']} evaluations, {record['seconds']:.0f} s): {'; '.join(record['changed'])}; "
            f"held-out {test.k}-step gap {g_nom:.4g} -> {g_cal:.4g} (shrink {record['shrink']:.1%}, sign-flip p {p:.2g})")
    else:
        log(f"  calibration ({evals['n']} evaluations): the nominal settings stay"
            + (f" (proposed {'; '.join(record['proposed'])} did not lower the held-out gap: {g_nom:.4g} -> {g_cal:.4g})"
               if best != Settings() else ""))
    return Calibration(model=base if ok else sm, settings=best if ok else Settings(), record=record, heldout=heldout)


def screen(base: SimModel, train: fit.Data, scale: np.ndarray, cfg: CalibrateConfig, grid: int,
           only: frozenset[str] | None = None) -> tuple[dict, dict]:
    """The scalar library effect that lowers the training loss most on top of ``base`` (every
    :func:`stride`-th replay): ``({name: value}, record)``, or ``({}, record)`` when none lowers
    it by ``min_gain``; ``only``: the effects to screen (all scalar candidates by default).

    Each effect is found by Gauss-Newton from its nominal value, every effect's replays in one
    batch: a secant replay at a tenth of its range gives the residual's slope and the linear
    least-squares estimate; then ``screen_steps - 1`` times, for the four effects with the
    lowest loss so far, the vertex of a parabola through the effect's three best points. Integer
    effects (delays) are scored on a grid of at most ``grid`` values. With ``cfg.refine_finer``
    (and no ``only``) the joint groups of the best joint effects are screened the same way after
    them and compete with them (one parameter each; :func:`held_choice`). It only picks the effect
    to hold fixed while the settings are fitted again (:func:`refine`); the effects' own fits come
    later, on the calibrated baseline."""
    sub = _sub(train, stride(cfg, len(train.start)))
    r0 = residual(base, sub, scale).ravel()
    L0 = float(r0 @ r0)
    pts: dict[str, dict[float, float]] = {}  # effect -> {value: loss}
    scalar = [e for e in effects.candidates(base) if e.size == 1 and (only is None or e.name in only)]

    def score(points):
        if not points:
            return []
        R = replay.residuals(base, [effects.build(base, {n: [x]}) for n, x in points], sub, scale)
        for (n, x), r in zip(points, R, strict=True):
            pts.setdefault(n, {})[x] = float((r ** 2).sum())
        return R

    def search(scalar):
        """Gauss-Newton from nominal for each of ``scalar``: a secant replay, the linear estimate,
        then parabola vertices for the four best of them."""
        ends = {e.name: tuple(float(b[0]) for b in e.bounds(base)) for e in scalar}
        first = []
        for e in scalar:
            lo, hi = ends[e.name]
            x0 = float(e.nominal[0])
            if e.integer:
                xs = np.unique(np.linspace(lo, hi, min(grid, int(hi - lo) + 1)).round())
                first += [(e.name, float(x)) for x in xs if abs(x - x0) > 1e-12]
            else:
                d = 0.1 * (hi - lo)
                first.append((e.name, x0 + d if x0 + d <= hi else x0 - d))
        R = score(first)
        est = []
        for (n, x1), r in zip(first, R, strict=True):
            e = effects.ALL[n]
            if e.integer:
                continue
            x0 = float(e.nominal[0])
            J = (r.ravel() - r0) / (x1 - x0)
            if J @ J > 0:
                lo, hi = ends[n]
                x = float(np.clip(x0 - (J @ r0) / (J @ J), lo, hi))
                if all(abs(x - v) > 1e-9 * (hi - lo) for v in (x0, x1)):
                    est.append((n, x))
        score(est)
        mine = [e.name for e in scalar if not e.integer and e.name in pts]
        for _ in range(cfg.screen_steps - 1):
            best4 = sorted(mine, key=lambda n: min(pts[n].values()))[:4]
            step = []
            for n in best4:
                lo, hi = ends[n]
                known = {float(effects.ALL[n].nominal[0]): L0} | pts[n]
                if len(known) < 3:
                    continue  # only the secant point so far: no parabola to draw
                (a, fa), (b, fb), (c, fc) = sorted(known.items(), key=lambda p: p[1])[:3]
                den = (b - a) * (fb - fc) - (b - c) * (fb - fa)
                if ((fa - fb) / (a - b) - (fb - fc) / (b - c)) / (a - c) <= 0:
                    continue  # no convex parabola through them
                x = float(np.clip(b - 0.5 * ((b - a) ** 2 * (fb - fc) - (b - c) ** 2 * (fb - fa)) / den, lo, hi))
                if all(abs(x - v) > 1e-6 * (hi - lo) for v in (a, b, c)):
                    step.append((n, x))
            score(step)

    search(scalar)
    kids = []
    if cfg.refine_finer and only is None:
        # the joint groups of the best joint effects: a group's effect that the logs carry (damping
        # on the calves) is also found, weaker, on every joint, and the settings fitted with the
        # all-joints effect held make up for the rest (the recheck, :func:`recheck`, repeated
        # the screen and the ranking for it: 507 s of a 5-minute target, results/gap_speed.md)
        coarse = sorted((n for n in pts if finer.children(base, n)), key=lambda n: min(pts[n].values()))
        kids = [effects.ALL[c] for n in coarse[:cfg.refine_finer] for c in finer.children(base, n)]
        search(kids)
        scalar = scalar + kids
    rows = []
    for e in scalar:
        if e.name in pts:
            x, fx = min(pts[e.name].items(), key=lambda p: p[1])
            rows.append({"effect": e.name, "value": x, "loss": fx})
    rows.sort(key=lambda r: r["loss"])
    rec = {"loss_without": L0, "screen": rows, "replays": sum(len(v) for v in pts.values())}
    pick, passed_over = held_choice(rows, {e.name for e in kids}, cfg.refine_finer_margin)
    if passed_over:
        rec["group_not_held"] = passed_over
    if pick and pick["loss"] < (1 - cfg.min_gain) * L0:
        return {pick["effect"]: [pick["value"]]}, rec
    return {}, rec


def held_choice(rows: list[dict], group: set[str], margin: float) -> tuple[dict | None, dict | None]:
    """The screen's row to hold among ``rows`` (``{"effect", "value", "loss"}``, lowest loss
    first) where the effects in ``group`` are joint groups: the first row, unless it is a group
    that does not remove ``margin`` of what the best library effect leaves (the ranking's finer
    rule, on the training loss: a hair's lead is no group's signature), then that library effect.
    Returns ``(row or None, the passed-over group's record or None)``."""
    pick = rows[0] if rows else None
    lib = next((r for r in rows if r["effect"] not in group), None)
    if pick and pick["effect"] in group and lib and pick["loss"] > (1 - margin) * lib["loss"]:
        return lib, {"group": pick["effect"], "loss": pick["loss"], "library": lib["effect"],
                     "library_loss": lib["loss"], "margin": margin}
    return pick, None


def refine(sm: SimModel, cal: Calibration, train: fit.Data, test: fit.Data, scale: np.ndarray,
           cfg: CalibrateConfig, grid: int, log=print) -> Calibration:
    """The settings fitted again with the best screened effect (:func:`screen`) held fixed on top,
    starting from the first calibration ``cal``; ``cal`` itself where no effect helps.

    An effect that *is* a calibrated setting (``contact_softness``: the solref time constant;
    :data:`stride_jax.gap.nominal.OVERLAPS`) is not held fixed but folded into the start of the
    search (the screen's 1-D search can find a time constant that the joint least squares missed);
    the best of the other effects is held fixed."""
    _, rec = screen(cal.model, train, scale, cfg, grid)
    gains = [r for r in rec["screen"] if r["loss"] < (1 - cfg.min_gain) * rec["loss_without"]]
    equiv = {n for n, setting in nominal.OVERLAPS.items() if setting in _names(cfg.continuous)}
    held = next(({r["effect"]: [r["value"]]} for r in gains if r["effect"] not in equiv), {})
    fold = {r["effect"]: [r["value"]] for r in gains if r["effect"] in equiv}
    start = nominal.fold_into(cal.settings, fold, _names(cfg.continuous))
    info = {"first_pass": cal.record["changed"], "screen": rec, "held_fixed": held, "folded": fold}
    if held or fold:
        log(f"  calibration refined with {held} held fixed on top and {fold} folded into the settings (screened)")
        cal2 = calibrate(sm, train, test, scale, cfg, log, applied=held or None, start=start, heldout=cal.heldout)
    else:
        cal2 = cal
    cal2, info["contact_effect_start"] = _contact_effect_start(sm, cal, cal2, held, train, test, scale, cfg, grid,
                                                               log)
    if info["contact_effect_start"].get("adopted"):
        info["held_fixed"], info["folded"] = info["contact_effect_start"]["held_fixed"], {}
    info["settings_moved"] = cal2.settings != cal.settings
    return dataclasses.replace(cal2, record=cal2.record | {"refined": info})


def recheck(sm: SimModel, cal: Calibration, best: dict, r_now: np.ndarray, train: fit.Data, test: fit.Data,
            scale: np.ndarray, cfg: CalibrateConfig, log=print) -> tuple[Calibration | None, dict]:
    """The settings fitted again with the diagnosis's best hypothesis ``best`` (``{effect:
    params}``, fitted on ``cal``'s baseline) held fixed on top, from the nominal model, the
    training form and ``cal``'s settings, whichever fits best (:func:`calibrate`); run only where
    ``best`` names other effects than the refinement held (:func:`refine`). Returns ``(the new
    calibration, record)`` where its held-out ``k``-step residual with ``best`` applied beats
    ``r_now`` (``cal``'s with ``best`` applied, ``[M, nv]`` on ``test``) by at least
    ``cfg.recheck_min`` of its gap and significantly (one-sided sign-flip test of the paired block
    improvements at ``cfg.recheck_p``), else ``(None, record)``. The bar is the pair rule's kind,
    not ``min_gain``: a small held-out gain came with settings that traded against the effect
    (the independent benchmark's noisy centre-of-mass offset: 2.5% better held out, the offset's
    x from 0.030, the planted value, to 0.021).

    The refinement holds the effect that its screen on the first calibration picks, and that
    calibration may already have imitated the right one with the contact settings, so the screen
    picks another (measured: the independent benchmark's torque limit 0.4 on logs whose simulator
    differs only in its 4 ms time step; the first calibration took feet-only contacts and softer
    contacts, its screen torque_scale 0.75, the diagnosis then named torque_limit 0.413 on that
    baseline, where the nominal model with the torque limit fits the training split 23x better:
    ``experiments/probes/form_spread.py --rows 06-clean --nominal``)."""
    held = (cal.record.get("refined") or {}).get("held_fixed") or {}
    rec: dict[str, Any] = {"best": {n: np.atleast_1d(v).tolist() for n, v in best.items()},
                           "refinement_held": held, "ran": False, "adopted": False}
    if not best or set(best) == set(held):
        return None, rec
    log(f"  calibration checked with the best hypothesis {sorted(best)} held fixed (the refinement held "
        f"{sorted(held) or 'none'})")
    new = calibrate(sm, train, test, scale, cfg, log, applied=best, start=cal.settings, heldout=cal.heldout)
    r_new = new.heldout[_heldout_key(new.settings, best)]  # replayed by the calibration's held-out check
    g_now, g_new = fit.gap(r_now), fit.gap(r_new)
    moved = new.settings != cal.settings
    p = paired_p(r_now, r_new, test, cfg.block, cfg.seed + 13) if moved else 1.0
    rec |= {"ran": True, "heldout_gap": g_new, "heldout_gap_before": g_now, "p_value": p, "settings_moved": moved,
            "adopted": bool(moved and g_new <= (1 - cfg.recheck_min) * g_now and p <= cfg.recheck_p)}
    log(f"  held-out {test.k}-step gap with {sorted(best)}: {g_new:.4g} against {g_now:.4g} (sign-flip p {p:.2g}; "
        f"needs {1 - cfg.recheck_min:.0%} of it or less at p <= {cfg.recheck_p:g}): "
        + ("adopted, effects scored again" if rec["adopted"] else "kept"))
    if not rec["adopted"]:
        return None, rec
    return dataclasses.replace(new, record=new.record | {"refined": cal.record.get("refined"), "recheck": rec}), rec


def contact_effect_screen(sm: SimModel, train: fit.Data, scale: np.ndarray, cfg: CalibrateConfig, grid: int
                          ) -> tuple[dict, dict, float]:
    """The contact effects that none of the calibrated settings reproduces
    (:data:`stride_jax.gap.nominal.OVERLAPS`: ground friction) screened on top of ``sm``
    (:func:`screen`): ``(best {name: value} or {}, the screen's record, the share of sm's training
    loss the best closes)``; ``({}, {}, 0.0)`` where there are none to screen."""
    names = frozenset(n for n, setting in nominal.OVERLAPS.items()
                      if setting is None or setting not in _names(cfg.continuous))
    if not names:
        return {}, {}, 0.0
    alt, rec = screen(sm, train, scale, cfg, grid, only=names)
    return alt, rec, (1 - rec["screen"][0]["loss"] / rec["loss_without"] if alt else 0.0)


def heldout_gap(cal: Calibration) -> float:
    """The held-out ``k``-step gap of ``cal``'s model with the effects it was fitted under applied
    (none: the calibrated gap)."""
    with_held = cal.record.get("heldout_gap_with_held")
    return cal.record["heldout_gap_calibrated"] if with_held is None else with_held


def _contact_effect_start(sm: SimModel, cal: Calibration, cal2: Calibration, held: dict, train: fit.Data,
                          test: fit.Data, scale: np.ndarray, cfg: CalibrateConfig, grid: int, log
                          ) -> tuple[Calibration, dict]:
    """A second start for the contact effects that no setting reproduces (``ground_friction``:
    :data:`stride_jax.gap.nominal.OVERLAPS`). The contact settings can imitate them, and a first
    calibration that did so ends in a basin where the effect helps little, so the screen on top of
    it proposes a value near nominal, if any, and the refinement starts from that basin (measured:
    a planted ground friction 0.3 on Go1 logs with independent contact settings; settings alone
    reach a held-out 3-step gap of 0.145 with the solref damping ratio at x 0.35 and impratio 6.6,
    the same search with friction 0.3 held fixed 0.048: ``experiments/probes/calibration_with_effect.py
    --case 8``; the screen on top of that first pass proposed 0.84). They are screened on the nominal
    model instead, and the best one, where it closes at least ``cfg.second_start`` of the nominal
    model's training loss on its own, is held fixed in a calibration from the start (the share
    keeps the extra calibration to effects strong enough to be the story, as the 50% rule names
    effects: measured on the independent benchmark's rows, a planted ground friction 0.3 closes
    83% clean and 68% noisy, friction proposed for a planted damping 3% and for a payload 28%,
    whose second starts fitted 9x and 60x worse held out). That calibration is adopted where its held-out gap (with
    the effect applied) is lower by ``min_gain`` than the other's (``cal2``: with its screened
    effect ``held`` applied, or the first pass's with none). The effect itself is then scored
    on the adopted settings like any other, by the rules that name effects."""
    alt, rec, share = contact_effect_screen(sm, train, scale, cfg, grid)
    if not rec:
        return cal2, {}
    out: dict[str, Any] = {"screen": rec, "held_fixed": alt, "share": share, "adopted": False}
    if not alt or alt == held or share < cfg.second_start:
        return cal2, out
    log(f"  calibration from the start with {alt} held fixed (screened on the nominal model: a contact effect "
        f"the settings can imitate)")
    cal3 = calibrate(sm, train, test, scale, cfg, log, applied=alt, heldout=cal.heldout)
    g_ref, g_alt = heldout_gap(cal2), heldout_gap(cal3)
    out |= {"heldout_gap": g_alt, "heldout_gap_other": g_ref,
            "adopted": bool(cal3.record["applied"] and g_alt < (1 - cfg.min_gain) * g_ref)}
    log(f"  held-out {test.k}-step gap with {alt}: {g_alt:.4g} against {g_ref:.4g}: "
        + ("adopted" if out["adopted"] else "not adopted"))
    return (cal3 if out["adopted"] else cal2), out
