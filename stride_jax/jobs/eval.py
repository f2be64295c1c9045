"""``stride eval``: the paper's Table I for trained runs ->
``results/table1/<robot>/table.{md,json}``.

For each run (a folder written by ``stride train``), on the test split of the dataset it was
trained on:

* **state**: cumulative normalised ``horizon``-step open-loop RMSE (``eval/rollout.py`` states the
  normalisation), also per horizon for the error-vs-horizon figure;
* **force** (structured models, robots with feet): mean absolute error (N) of each stance foot's
  vertical force recovered from the predicted residual through the contact Jacobians
  (``eval/forces.py``), per foot and overall, with the oracle floor of that map;
* **share**: the residual's share of the predicted acceleration in free motion and in contact
  (any foot -- for the bouncing pendulum its bob -- carrying a contact force).

* **distribution** (``eval/distribution.py``): the mean-of-samples error, the energy score and
  CRPS of the ``samples`` rollouts, and the coverage of their range, against the logged future
  and ``continuations`` more true futures re-simulated from the same start state under new draws
  of the hidden randomness (``sim/continuations.py``; made once per dataset and settings, cached
  in the dataset's folder).

Stochastic models are evaluated ``samples`` times with independent latents (19 by default: their
range is then a 90% interval); a run reports the mean over samples and their spread (std). Forces
are also read from the residual's central sample and from the mean of the samples' residuals.
Runs of one model with different seeds are then aggregated into a mean and a std over seeds,
which is what the table shows.
"""

from __future__ import annotations

import dataclasses
import glob
import json
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from stride_jax.dynamics import checkpoint, models
from stride_jax.eval import distribution, forces, rollout, runs as runs_lib
from stride_jax.sim import continuations, dataset, model as sim_model, record
from stride_jax.io import atomic_write, atomic_write_text, code_version


@dataclasses.dataclass(frozen=True)
class EvalConfig:
    """What ``stride eval`` evaluates.

    Attributes:
      runs: comma-separated run folders or globs (e.g. ``runs/go1/*``).
      horizon: open-loop rollout length (control steps).
      windows: rollout windows drawn from the test split.
      samples: latent samples per stochastic model.
      continuations: true futures per window re-simulated under new hidden draws (0: the
        logged one only).
      force_steps: test steps used for the force error and the residual share.
      nfe: evaluations per residual sample; 0 means each model's trained default.
      diverged_above: a rollout whose normalised error exceeds this anywhere (a thousand times
        the data's spread by default) has diverged, as one that left the floating-point range:
        counted, not averaged (a finite 1e13 would otherwise swamp every mean).
      latents: a stochastic model's latents in a rollout: drawn afresh at every control step
        (``step``, as trained) or once per rollout (``rollout``: what the model does not know
        persists; ``dynamics.models.rollout_keys``). Rows of ``rollout`` get their own label.
      out: output folder; empty means ``results/table1/<robot>``.
      seed: windows, steps and latents.
      label: the command to record as having made the table (default: this ``stride eval``).
    """

    runs: str = "runs/pendulum/*"
    horizon: int = 30
    windows: int = 256
    samples: int = 19
    continuations: int = 8
    force_steps: int = 1024
    nfe: int = 0
    diverged_above: float = 1e3
    latents: str = "step"
    out: str = ""
    seed: int = 0
    label: str = ""

    def __post_init__(self):
        if self.latents not in models.LATENTS:
            raise ValueError(f"latents must be one of {models.LATENTS}, got {self.latents!r}")
        if not self.diverged_above > 0:
            raise ValueError(f"diverged_above must be > 0, got {self.diverged_above!r}")


PRESETS = {"tiny": EvalConfig(horizon=10, windows=32, samples=3, force_steps=128,
                           continuations=2),
           "default": EvalConfig()}


def find_runs(pattern: str) -> list[pathlib.Path]:
    runs = sorted({pathlib.Path(p) for part in pattern.split(",") if part
                   for p in glob.glob(part.strip()) if (pathlib.Path(p) / "model.json").is_file()})
    if not runs:
        raise FileNotFoundError(f"no training runs (folders with model.json) match {pattern!r}")
    unsaved = [str(r) for r in runs if not runs_lib.is_trained(r)]
    if unsaved:  # a run killed before its first evaluation, or a folder that is not a run
        raise FileNotFoundError(f"run(s) {unsaved} have no summary.json (no checkpoint saved yet): "
                                "resume them with the same `stride train` command, or leave them out")
    return runs


def _label(name: str, train: dict) -> str:
    """A model's row in the table: its name, with the training variant when it is not the
    default (``stride[acc_through=prior]``), so ablations get rows of their own."""
    through = train.get("acc_through", "central")
    generative = models.MODELS.get(name, ("", None))[1] not in (None, "mlp", "none")
    structured = models.MODELS.get(name, ("",))[0] == "structured"
    variant = [f"acc_through={through}"] if structured and generative and through != "central" \
        else []
    variant += ["learn_mass"] if structured and train.get("learn_mass") else []
    variant += ["no_base_structure"] if structured and not train.get("base_structure", True) \
        else []
    variant += [f"potential={train['potential']}"] if structured and train.get(
        "potential", "net") != "net" else []
    return f"{name}[{','.join(variant)}]" if variant else name


def evaluate_run(run: pathlib.Path, cfg: EvalConfig) -> dict:
    """One run's metrics (see the module docstring)."""
    model, params = checkpoint.load(run)
    run_cfg = json.loads((run / "config.json").read_text())
    trained_nfe = json.loads((run / "model.json").read_text())["config"]["nfe"]
    ds = dataset.load(run_cfg["dataset"])
    spec = models.spec_from_meta(ds.meta)
    test, train = ds.split("test"), ds.split("train")
    nfe = cfg.nfe or None
    key = jax.random.key(cfg.seed)
    n_samples = cfg.samples if model.stochastic else 1
    label = _label(model.name, run_cfg["train"])
    if model.stochastic and cfg.latents != "step":
        label = f"{label[:-1]},latents={cfg.latents}]" if label.endswith("]") \
            else f"{label}[latents={cfg.latents}]"
    out = {"run": str(run), "model": label, "latents": cfg.latents if model.stochastic else None,
           "seed": runs_lib.train_seed(run_cfg["train"]),
           "robot": ds.meta["robot"], "params": int(sum(x.size for x in jax.tree.leaves(params))),
           "stochastic": model.stochastic, "nfe": (nfe or trained_nfe) if model.stochastic else None,
           "steps_done": json.loads((run / "summary.json").read_text()).get("steps_done")}

    # State: cumulative open-loop RMSE, per sample.
    starts = rollout.windows(test["valid"], cfg.horizon, cfg.windows, cfg.seed)
    obs_scales = rollout.observation_scales(train, spec, cfg.horizon)
    told = models.takes_gravity(model)  # sloped data: each window's gravity, where it can
    rollout_fn = lambda p, q, qd, u, k, down=None: model.rollout(
        p, q, qd, u, k, nfe, cfg.latents, down if told else None)
    sample_keys = jax.vmap(lambda s: jax.random.fold_in(key, s))(jnp.arange(n_samples))
    vectors = rollout.rollout_error_vectors(rollout_fn, params, test, spec, cfg.horizon, starts,
                                            obs_scales, sample_keys)  # [S, N, H, D]
    runaway = ~(np.abs(vectors) <= cfg.diverged_above).all((-2, -1), keepdims=True)
    vectors = np.where(runaway, np.nan, vectors)  # diverged: non-finite or beyond the bound
    errs = rollout.per_horizon_rmse(vectors)  # [S, N, H]
    truths = true_futures(ds, test, spec, starts, cfg, obs_scales)
    out["distribution"] = distribution.scores(vectors, truths)
    # A diverged rollout (above) is counted, not averaged.
    finite = np.isfinite(errs).all(-1)  # [S, N]
    cum = np.array([errs[s][finite[s]].sum(-1).mean() if finite[s].any() else np.nan
                    for s in range(n_samples)])
    kept = np.maximum(finite.sum((0, 1)), 1)  # every rollout diverged: NaN, without a warning
    per_h = np.where(finite[..., None], errs, 0.0).sum((0, 1)) / kept
    per_h = np.where(finite.any(), per_h, np.nan)
    out["state"] = {"mean": float(cum.mean()), "spread": float(cum.std()),
                    "per_horizon": per_h.tolist(), "windows": len(starts),
                    "diverged": float(1.0 - finite.mean())}
    if model.terms is None:
        return out

    # Residual: force error through the contact Jacobians, and the residual's share.
    valid = np.argwhere(test["valid"])
    rng = np.random.default_rng(cfg.seed)
    idx = valid[rng.permutation(len(valid))[:cfg.force_steps]]
    pick = lambda k: np.asarray(test[k][idx[:, 0], idx[:, 1]], np.float32)
    q, qd, tau = pick("q"), pick("qd"), pick("tau")
    down = record.down_of(test)  # sloped data: each step's gravity, told to the models
    down = None if down is None else np.asarray(down[idx[:, 0], idx[:, 1]])
    terms_fn = jax.jit(jax.vmap(lambda q, qd, tau, k, d: model.terms(params, q, qd, tau, k, nfe,
                                                                     d)))
    terms = [terms_fn(q, qd, tau, jax.random.split(jax.random.fold_in(key, 1000 + s), len(q)),
                      down) for s in range(n_samples)]
    for t in terms[1:]:  # M is the same for every sample: keep one copy ([N, nv, nv] each)
        t.pop("mass", None)
    qdd_scale = np.asarray(train["qdd"][train["valid"]].std(0)) + 1e-6
    contact = pick("foot_contact").any(-1)  # robots without feet are always in free motion
    shares = np.stack([forces.residual_share(np.asarray(t["prior"]), np.asarray(t["residual"]),
                                             qdd_scale) for t in terms])  # [S, N]
    out["share"] = {
        region: {"mean": float(shares[:, mask].mean()) if mask.any() else None,
                 "spread": float(shares[:, mask].mean(1).std()) if mask.any() else None,
                 "steps": int(mask.sum())}
        for region, mask in (("free", ~contact), ("contact", contact))}

    sm = sim_model.load(ds.meta["robot"])
    if sm.nfeet == 0 or not spec.floating_base:  # ground reaction forces: legged robots
        return out
    jac = forces.foot_jacobians(sm, q)
    stance = pick("foot_contact") > 0.5
    true_normal = pick("foot_force")
    true_eps = pick("qfrc_passive") + pick("qfrc_constraint") + pick("qfrc_external")
    per_sample = np.stack([forces.normal_force_errors(jac, stance, np.asarray(t["eps"]),
                                                      true_normal) for t in terms])  # [S, N, F]
    oracle = forces.normal_force_errors(jac, stance, true_eps, true_normal)
    mean_eps = np.mean([np.asarray(t["eps"]) for t in terms], axis=0)
    of_mean = forces.normal_force_errors(jac, stance, mean_eps, true_normal)
    central = jax.jit(jax.vmap(lambda q, qd, tau, d: model.terms(params, q, qd, tau, None, nfe,
                                                                 d)))
    of_central = forces.normal_force_errors(
        jac, stance, np.asarray(central(q, qd, tau, down)["eps"]), true_normal)
    # The prior's own inverse dynamics with the true acceleration: r* = M (qdd - f_LNN), read
    # through the same map (no residual involved; the only force readout of a prior-only model).
    implied = np.einsum("nij,nj->ni", np.asarray(terms[0]["mass"]),
                        pick("qdd") - np.asarray(terms[0]["prior"]))
    of_prior = forces.normal_force_errors(jac, stance, implied, true_normal)
    sample_means = np.nanmean(per_sample, axis=(1, 2))
    out["force"] = {
        "mean": float(sample_means.mean()), "spread": float(sample_means.std()),
        "per_foot": dict(zip((f.name for f in sm.robot.feet),
                             np.nanmean(per_sample, axis=(0, 1)).tolist())),
        "oracle": float(np.nanmean(oracle)), "stance_feet": int(stance.sum()),
        "of_sample_mean": float(np.nanmean(of_mean)),
        "of_central": float(np.nanmean(of_central)),
        "of_prior": float(np.nanmean(of_prior)),
        "mean_true_normal": float(true_normal[stance].mean())}
    return out


def true_futures(ds: dataset.Dataset, split: dict, spec, starts: np.ndarray, cfg: EvalConfig,
                 obs_scales) -> np.ndarray | None:
    """``[N, 1 + K, H, D]``: the logged future of each window (zeros) and ``K =
    cfg.continuations`` more re-simulated under new draws of the dataset's hidden randomness, in
    the normalised error coordinates against the logged future (``None`` for none). Cached in ``<dataset>/continuations/`` (the same
    windows and draws serve every run on the dataset)."""
    if cfg.continuations <= 0:
        return None
    key = f"h{cfg.horizon}-w{len(starts)}-k{cfg.continuations}-s{cfg.seed}"
    cache = ds.path / "continuations" / f"{key}-{ds.meta['arrays_sha256'][:12]}.npz"
    if cache.is_file():
        return np.load(cache)["truths"]
    sm = sim_model.load(ds.meta["robot"])
    q, qd, ctrl = (np.asarray(a) for a in rollout.window_arrays(split, starts, cfg.horizon))
    ctrl_dt = ds.meta["ctrl_dt"]
    futures = continuations.simulate(
        sm, continuations.randomization_of(ds.meta), q[:, 0], qd[:, 0], ctrl,
        starts[:, 1] * ctrl_dt, split["q"].shape[1] * ctrl_dt, cfg.continuations,
        jax.random.key(cfg.seed + 7919), down=rollout.window_down(split, starts))
    err = jax.jit(jax.vmap(jax.vmap(
        lambda a, b, c, d: rollout.normalised_errors(a, b, c, d, obs_scales, spec.floating_base),
        in_axes=(0, 0, None, None))))
    truths = np.asarray(err(jnp.asarray(futures.q, jnp.float32), jnp.asarray(futures.qd,
                                                                            jnp.float32),
                            q[:, 1:], qd[:, 1:]))
    # A future that fell or diverged is no future the models are asked to predict.
    truths = np.where(futures.valid[..., None, None], truths, np.nan)
    keep = np.isfinite(truths).all((2, 3))
    truths = np.where(keep[..., None, None], truths, 0.0)  # fallen: the logged future instead
    truths = np.concatenate([np.zeros_like(truths[:, :1]), truths], axis=1)  # the logged one
    cache.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(cache, lambda f: np.savez(f, truths=truths.astype(np.float32)))
    return truths


def _cached(run: pathlib.Path, cfg: EvalConfig) -> dict:
    """``evaluate_run``, reusing ``run/eval.json`` when it was made with the same settings from
    the same best checkpoint (so runs can be evaluated in parallel, then tabulated)."""
    key = {k: v for k, v in dataclasses.asdict(cfg).items() if k not in ("runs", "out", "label")}
    key["best_step"] = json.loads((run / "summary.json").read_text()).get("best_step")
    if cfg.latents == "step":  # the caches written before the choice existed stay valid
        del key["latents"]
    cache = run / ("eval.json" if cfg.latents == "step" else f"eval-latents-{cfg.latents}.json")
    if cache.is_file():
        saved = json.loads(cache.read_text())
        if saved.get("key") == key:
            return saved["result"]
    result = evaluate_run(run, cfg)
    atomic_write_text(cache, json.dumps({"key": key, "result": result}, indent=1))
    return result


def _agg(values: list) -> dict | None:
    values = [v for v in values if v is not None]
    if not values:
        return None
    return {"mean": float(np.mean(values)), "std": float(np.std(values)), "n": len(values)}


def aggregate(results: list[dict]) -> dict[str, dict]:
    """Per model: mean and std over seeds of each headline metric."""
    by_model: dict[str, list[dict]] = {}
    for r in results:
        by_model.setdefault(r["model"], []).append(r)
    get = lambda r, *path: _dig(r, path)
    table = {}
    for name in [m for m in models.MODELS if m in by_model] + sorted(set(by_model) - set(
            models.MODELS)):
        rs = by_model[name]
        table[name] = {
            "seeds": sorted(r["seed"] for r in rs), "params": rs[0]["params"],
            "steps_done": sorted({r.get("steps_done") for r in rs}, key=str),
            "state": _agg([get(r, "state", "mean") for r in rs]),
            "state_sample_spread": _agg([get(r, "state", "spread") for r in rs]),
            "diverged": _agg([get(r, "state", "diverged") for r in rs]),
            "force": _agg([get(r, "force", "mean") for r in rs]),
            "force_oracle": _agg([get(r, "force", "oracle") for r in rs]),
            "force_of_mean": _agg([get(r, "force", "of_sample_mean") for r in rs]),
            "share_free": _agg([get(r, "share", "free", "mean") for r in rs]),
            "share_contact": _agg([get(r, "share", "contact", "mean") for r in rs]),
            "force_of_central": _agg([get(r, "force", "of_central") for r in rs]),
            "force_of_prior": _agg([get(r, "force", "of_prior") for r in rs]),
            **{f"dist_{k}": _agg([get(r, "distribution", k) for r in rs])
               for k in ("mean_of_samples", "energy", "crps", "coverage", "nominal_coverage")},
        }
    return table


def _dig(d, path):
    for k in path:
        if not isinstance(d, dict) or d.get(k) is None:
            return None
        d = d[k]
    return d


def _fmt(a: dict | None, digits: int = 3, pct: bool = False) -> str:
    if a is None:
        return "n/a"
    f = 100.0 if pct else 1.0
    s = f"{f * a['mean']:.{digits}f}"
    return s + (f" ± {f * a['std']:.{digits}f}" if a["n"] > 1 else "")


def markdown(table: dict, robot: str, command: str, cfg: EvalConfig) -> str:
    lines = [f"# {robot}: open-loop accuracy (the paper's Table I on our data)", "",
             f"Command: `{command}`", "",
             f"State: cumulative normalised {cfg.horizon}-step RMSE on the test split "
             f"({cfg.windows} windows max). Force: mean |error| of stance feet's vertical force (N) "
             "from the residual through the contact Jacobians; oracle = the same map applied to "
             "the true residual; 'of sample mean': the force read from the mean residual over "
             "samples. Share: residual's share of the predicted acceleration (%). "
             "Diverged: rollouts that left the floating-point range or exceeded `diverged_above` (%), excluded from the RMSE. "
             "Values: mean ± std over seeds.", "",
             "| model | params | seeds | steps | state RMSE | diverged (%) | force error (N) | "
             "of sample mean (N) | force oracle (N) | share free (%) | share contact (%) |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, row in table.items():
        lines.append(
            f"| {name} | {row['params']:,} | {len(row['seeds'])} | "
            f"{'/'.join(str(x) for x in row['steps_done'])} | {_fmt(row['state'])} | "
            f"{_fmt(row['diverged'], 1, True)} | {_fmt(row['force'], 1)} | "
            f"{_fmt(row['force_of_mean'], 1)} | {_fmt(row['force_oracle'], 1)} | "
            f"{_fmt(row['share_free'], 1, True)} | {_fmt(row['share_contact'], 1, True)} |")
    lines += ["", f"Distributions ({cfg.samples} samples of each stochastic model against the "
              f"logged future and {cfg.continuations} re-simulated ones under new hidden draws, "
              "`eval/distribution.py`): error of the samples' mean, energy score and CRPS "
              "(normalised units, lower is better), coverage of the samples' range (%) against "
              "its nominal level; force read from the residual's central sample (N), and from "
              "the residual the prior implies with the true acceleration, M (qdd - f_LNN): the "
              "prior's own inverse dynamics, no residual involved (N).", "",
              "| model | state RMSE per sample | of sample mean | energy score | CRPS | "
              "coverage (%) | nominal (%) | force, central sample (N) | force, prior's "
              "inverse dynamics (N) |",
              "|---|---|---|---|---|---|---|---|---|"]
    for name, row in table.items():
        lines.append(
            f"| {name} | {_fmt(row['state'])} | {_fmt(row.get('dist_mean_of_samples'))} | "
            f"{_fmt(row.get('dist_energy'))} | {_fmt(row.get('dist_crps'))} | "
            f"{_fmt(row.get('dist_coverage'), 1, True)} | "
            f"{_fmt(row.get('dist_nominal_coverage'), 1, True)} | "
            f"{_fmt(row.get('force_of_central'), 1)} | "
            f"{_fmt(row.get('force_of_prior'), 1)} |")
    ratios = _ratios(table)
    if ratios:
        lines += ["", "Ratios (ours; the paper's Go1 / G1 in brackets):", ""]
        lines += [f"- {k}: {v:.3g}" for k, v in ratios.items()]
    return "\n".join(lines) + "\n"


def _ratios(table: dict) -> dict[str, float]:
    m = lambda name, key: _dig(table, (name, key, "mean"))
    out = {}
    pairs = [("STRIDE/DeLaN state RMSE [0.70 / 0.28]", "delan", "state"),
             ("STRIDE/DeLaN force error [0.71 / 0.71]", "delan", "force"),
             ("STRIDE/(LNN+Diffusion) state RMSE [0.81 / 0.31]", "lnn_diffusion", "state"),
             ("STRIDE/ONN state RMSE [0.17 / 0.47]", "onn", "state"),
             ("STRIDE/DeLaN as published (prior only) state RMSE", "delan_prior", "state"),
             ("STRIDE/DeLaN energy score", "delan", "dist_energy"),
             ("STRIDE/DeLaN CRPS", "delan", "dist_crps")]
    for label, other, key in pairs:
        a, b = m("stride", key), m(other, key)
        if a is not None and b:
            out[label] = a / b
    return out


def _write(out: pathlib.Path, robot: str, cfg: EvalConfig, command: str, results: list[dict],
           run_configs: dict, **fields) -> None:
    """``out/table.json`` (settings, the aggregated table and its ratios, every run's result and
    config, then ``fields``) and ``out/table.md``: what ``run`` and ``merge`` write alike."""
    out.mkdir(parents=True, exist_ok=True)
    table = aggregate(results)
    atomic_write_text(out / "table.json", json.dumps(
        {"command": command, "config": dataclasses.asdict(cfg), "table": table,
         "ratios": _ratios(table), "runs": results, "run_configs": run_configs, **fields},
        indent=1))
    atomic_write_text(out / "table.md", markdown(table, robot, command, cfg))


def run(cfg: EvalConfig, command: str = "stride eval", log=print) -> pathlib.Path:
    code = code_version()  # the code this process runs: read now, not when the table is written
    runs = find_runs(cfg.runs)
    results = []
    t0 = time.time()
    for r in tqdm(runs, desc="eval", unit="run"):
        results.append(_cached(r, cfg))
    robots = {r["robot"] for r in results}
    if len(robots) != 1:
        raise ValueError(f"runs mix robots {sorted(robots)}; evaluate one robot at a time")
    robot = robots.pop()
    out = pathlib.Path(cfg.out or f"results/table1/{robot}")
    _write(out, robot, cfg, cfg.label or command, results,
           {str(r): json.loads((r / "config.json").read_text()) for r in runs},
           backend=jax.default_backend(), code=code, seconds=time.time() - t0)
    log(f"wrote {out / 'table.md'} and table.json ({len(runs)} runs)")
    return out


def merge(base: str | pathlib.Path, update: str | pathlib.Path, out: str | pathlib.Path,
          other_data: bool = False, log=print) -> pathlib.Path:
    """One table from two ``table.json`` files of the same robot and dataset: every model that
    ``update`` evaluated replaces that model's rows in ``base`` (e.g. one model retrained to the
    full step count in a later GPU call), the rest stay. Refuses tables made with different
    evaluation settings, robots or datasets (their numbers would not be comparable), unless
    ``other_data``: the same generator and settings regenerated into another dataset (its rows
    then come from other samples of the same distribution; the table names both digests)."""
    a, b = (json.loads(pathlib.Path(p).read_text()) for p in (base, update))
    ignore = ("runs", "out", "label")
    ca, cb = ({k: v for k, v in t["config"].items() if k not in ignore} for t in (a, b))
    if ca != cb:
        diff = sorted(k for k in set(ca) | set(cb) if ca.get(k) != cb.get(k))
        raise ValueError(f"{base} and {update} were evaluated with different settings: {diff}")
    robots = {r["robot"] for r in a["runs"] + b["runs"]}
    if len(robots) != 1:
        raise ValueError(f"{base} and {update} mix robots {sorted(robots)}")
    digests = {c.get("dataset_sha256") for t in (a, b) for c in t["run_configs"].values()}
    if len(digests) != 1 and not other_data:
        raise ValueError(f"{base} and {update} were trained on different datasets "
                         f"(sha256 {sorted(str(d)[:12] for d in digests)})")
    replaced = {r["model"] for r in b["runs"]}
    runs = [r for r in a["runs"] if r["model"] not in replaced] + b["runs"]
    dropped = {r["run"] for r in a["runs"] if r["model"] in replaced}
    configs = {k: v for k, v in a["run_configs"].items() if k not in dropped}
    configs.update(b["run_configs"])
    command = (f"{a['command']}; then {', '.join(sorted(replaced))} from: {b['command']}; "
               f"merged by stride_jax.jobs.eval.merge")
    datasets = {}  # model -> the first 12 hex digits of its runs' datasets' sha256
    for r in runs:
        digest = configs.get(r["run"], {}).get("dataset_sha256") or "unknown"
        datasets.setdefault(r["model"], set()).add(digest[:12])
    datasets = {m: sorted(d) for m, d in datasets.items()}
    if len(digests) != 1:
        command += (" (the later rows on a regenerated dataset of the same generator and "
                    "settings: dataset sha256 per model " + ", ".join(
                        f"{m} {'/'.join(d)}" for m, d in sorted(datasets.items())) + ")")
    codes = lambda t: t["code"] if isinstance(t["code"], list) else [t["code"]]  # merged: a list
    out = pathlib.Path(out)
    _write(out, robots.pop(), EvalConfig(**ca, **{k: a["config"][k] for k in ignore}), command,
           runs, configs, backend=a["backend"], code=sorted({*codes(a), *codes(b)}),
           merged_from=[a["command"], b["command"]], datasets=datasets,
           seconds=a["seconds"] + b["seconds"])
    log(f"wrote {out / 'table.md'} and table.json: {sorted(replaced)} from {update}")
    return out
