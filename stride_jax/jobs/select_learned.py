"""``stride select-learned``: which learned reward and value to plan with, chosen by the closed
loop they serve on validation episodes, not by their held-out R^2 and not on the benchmark's
scenarios.

Why: over one G1 policy, single fits of the reward and value moved the planner's tracking on rough
ground by 0.012 m/s and their held-out R^2 ranked them wrongly (session 93,
``results/closed_loop/g1_uphill_cpu/``); picking a fit by the scenarios the targets are read on
would fit the benchmark. Here every candidate file plans the same validation episodes: ``worlds``
closed-loop episodes side by side on the nominal ground, each a schedule of commands drawn from
the policy's training distribution (a new one every ``change_s``), the same draws and the same
planner keys for every candidate (paired). Each candidate's score is its planner's velocity
tracking RMSE (:func:`stride_jax.control.episode.metrics`), falls first; the table gives each
candidate's difference from the best with a paired 90% t-interval over the worlds, and the policy
alone on the same episodes (``policy_reference``; a reference, never ranked) says whether the best
planner tracks closer than its own fallback does, and each episode's error under each of its
commands (:func:`stride_jax.control.episode.piece_errors`) says where: the table groups them by
the command (stops; slow or fast, lateral, turning: :func:`by_command`).

    stride select-learned --robot g1 --policy results/policies/ppo_g1_uphill \\
        --model stride=results/models/g1_walk_ppo_g1_slope_slope15_tw1_tf0.25/stride-s0 \\
        --candidates soft=results/learned_g1_soft/reward_value.msgpack,\\
uphill=results/learned_g1_uphill/reward_value.msgpack \\
        --mppi.horizon 10 --planning.model-gravity --out results/select_learned_g1

Writes ``OUT/selection.{json,md}`` after each candidate, ranked over those done so far; run again
with the same settings and ``--out`` (more candidates welcome), it plans only the candidates not
yet there (a call cut by its time limit keeps what it finished). The planner is built as the
closed loop builds it from the same ``--mppi.*`` and ``--planning.*`` flags (give the headline's
to choose for the headline; the flat aliases such as ``--prior-noise-std`` are the closed
loop's alone: here ``--planning.prior-noise-std``). Its model options are the closed loop's too:
``--kernel``, ``--model-precision``, ``--model-substeps``, ``--error-model``, and the sensors the
controller sees through (``--sensor-noise``, ``--sensors.*``); latency is
``--planning.latency-s`` (the closed loop's ``--latency-auto`` measures it per planner; give the
time it measured).
"""

from __future__ import annotations

import dataclasses
import json
import pathlib
import time

import jax
import numpy as np

import stride_jax
from stride_jax import config
from stride_jax.control import envs, episode as episode_lib, learned as learned_lib, ppo
from stride_jax.control import planning as planning_lib
from stride_jax.control.mppi import MPPIConfig
from stride_jax.control.planning import PlanningConfig
from stride_jax.io import atomic_write_text, code_version, file_sha256
from stride_jax.sim import model as sim_model
from stride_jax.sim.sensors import SensorNoise, seen_through


@dataclasses.dataclass(frozen=True)
class SelectConfig:
    """Candidate learned reward/value files, planned with on the same validation episodes.

    Attributes:
      robot: go1 or g1.
      model: the planner's dynamics model, ``NAME=RUN`` (a trained run) or ``oracle`` (the
        simulator itself).
      policy: PPO run folder: the planner's policy (candidates, prior, fallback) and the
        commands' distribution.
      candidates: ``LABEL=PATH,...`` of ``reward_value.msgpack`` files (``stride
        fit-reward-value``; ensembles are planned with as the closed loop plans with them).
      worlds: validation episodes side by side (the paired sample).
      seconds: each episode's length (s).
      change_s: a new command every this long (s).
      settle_s: tracking errors count from this long after each command change (s).
      mppi: the planner's settings (``--mppi.samples`` ...), as the closed loop's.
      planning: the task's settings (``--planning.model-gravity`` ...), as the closed loop's.
      kernel: how structured models run their networks (``xla``, ``pallas-step`` ...).
      model_precision: matmul precision of the model's steps (the closed loop's).
      model_substeps: structured models integrate each control period in this many substeps
        (0: as trained; the closed loop's).
      error_model: a learned one-step error model of the planner's model (the closed loop's).
      sensor_noise: the controller sees the state through ``sensors`` at this factor (0: the
        exact state; the closed loop's).
      sensors: the sensors' terms (``--sensors.*``), used where ``sensor_noise`` > 0.
      seed: the commands' draws and the planner's keys.
      policy_reference: the policy alone on the same episodes too, as a reference (not a
        candidate): whether the planner tracks closer than its own fallback does.
      out: folder for ``selection.{json,md}``.
    """

    robot: str = "go1"
    model: str = "oracle"
    policy: str = "results/policies/ppo_go1"
    candidates: str = ""
    worlds: int = 16
    seconds: float = 4.0
    change_s: float = 1.0
    settle_s: float = 0.5
    mppi: MPPIConfig = MPPIConfig(samples=1024, horizon=20, policy_samples=64)
    planning: PlanningConfig = PlanningConfig()
    kernel: str = "xla"
    model_precision: str = ""
    model_substeps: int = 0
    error_model: str = ""
    sensor_noise: float = 0.0
    sensors: SensorNoise = SensorNoise()
    seed: int = 0
    policy_reference: bool = True
    out: str = "results/select_learned"  # not learned_*: SHA256SUMS lists those as fits

    def __post_init__(self):
        labels = [label for label, _ in self.pairs()]  # (none yet: a preset; run() asks)
        if len(set(labels)) != len(labels):
            raise ValueError(f"candidates: labels repeat ({', '.join(labels)})")
        name, _, run = self.model.partition("=")
        if self.model != "oracle" and not (name and run):
            raise ValueError(f"model must be NAME=RUN (a trained dynamics model) or oracle, got "
                             f"{self.model!r}")
        if self.worlds < 2:
            raise ValueError(f"worlds={self.worlds}: the paired intervals need at least 2")
        if not (self.seconds > 0 and self.change_s > 0):
            raise ValueError(f"seconds={self.seconds} and change_s={self.change_s} must be > 0")
        if not self.policy:
            raise ValueError("policy: the planner's policy and the commands' distribution")
        if self.model_substeps < 0:
            raise ValueError(f"model_substeps={self.model_substeps}: >= 0 (0: as trained)")
        if self.model_precision not in episode_lib.PRECISIONS:
            raise ValueError(f"model_precision={self.model_precision!r}: one of "
                             f"{', '.join(repr(p) for p in episode_lib.PRECISIONS)}")
        if self.model == "oracle" and (self.model_substeps or self.error_model
                                       or self.model_precision):
            raise ValueError("model_substeps, model_precision and error_model are a learned "
                             "model's; the oracle plans through the simulator itself")
        seen_through(self.sensors, self.sensor_noise)  # a clear error for a bad pair

    def pairs(self) -> list[tuple[str, str]]:
        """``[(label, path)]`` of ``candidates``."""
        out = []
        for item in (s for s in self.candidates.split(",") if s):
            label, sep, path = item.partition("=")
            if not (sep and label and path):
                raise ValueError(f"candidates: {item!r} is not LABEL=PATH")
            out.append((label, path))
        return out


PRESETS = {
    "tiny": SelectConfig(worlds=2, seconds=0.1, change_s=0.05, settle_s=0.0,
                         mppi=MPPIConfig(samples=8, horizon=3, policy_samples=2),
                         out="results/select_learned_tiny"),
    "default": SelectConfig(),
}


def paired(x: np.ndarray, y: np.ndarray, level: float = 0.9) -> dict | None:
    """``mean(x - y)`` over paired values with its ``level`` t-interval; None with fewer than
    two pairs or no spread in the differences."""
    from scipy import stats

    d = np.asarray(x, float) - np.asarray(y, float)
    if len(d) < 2 or not np.std(d) > 0:
        return None
    ci = stats.ttest_1samp(d, 0.0).confidence_interval(level)
    return dict(diff=float(d.mean()), lo=float(ci.low), hi=float(ci.high), n=len(d))


def rank(rows: list[dict]) -> list[dict]:
    """The candidates best first: fewer falls, then the lower mean tracking RMSE over the worlds
    that stayed up; each with its paired difference from the best over the worlds both kept up
    (``vs_best``; None for the best itself)."""
    order = sorted(rows, key=lambda r: (r["falls"], np.nan_to_num(r["vel_rmse"], nan=np.inf)))
    best = order[0]
    for r in order:
        r["vs_best"] = None if r is best else versus(r, best)
    return order


def interval(v: dict | None) -> str:
    """A :func:`paired` result as the tables write it: ``+d [lo, hi]``, or n/a."""
    return "n/a" if v is None else f"{v['diff']:+.4f} [{v['lo']:+.4f}, {v['hi']:+.4f}]"


def versus(row: dict, other: dict) -> dict | None:
    """:func:`paired` of two rows' per-episode errors over the episodes both kept up."""
    both = [i for i, (a, b) in enumerate(zip(row["fell"], other["fell"])) if not (a or b)]
    return paired(np.asarray(row["per_world"])[both], np.asarray(other["per_world"])[both])


def command_groups(commands, bounds) -> list[tuple[str, np.ndarray]]:
    """The validation commands ``[W, P, 3]`` (each episode's per piece) in :func:`by_command`'s
    groups: ``[(label, mask [W, P])]``, stops (all zero) first, then each component at or above
    half its range's largest magnitude (``bounds``: the commands' ``(lo [3], hi [3])``) or
    below it, among the moving pieces (a piece may sit in several)."""
    cmd = np.asarray(commands, float)
    scale = np.maximum(np.abs(np.asarray(bounds[0], float)), np.abs(np.asarray(bounds[1], float)))
    big = np.abs(cmd) >= 0.5 * np.where(scale > 0, scale, np.inf)  # [W, P, 3]
    stop = np.all(cmd == 0, axis=-1)
    groups = [("stops (all zero)", stop)]
    for i, name in enumerate(("forward", "lateral", "yaw rate")):
        half = 0.5 * scale[i]
        signs = " (either sign)" if bounds[0][i] < 0 < bounds[1][i] else ""
        groups += [(f"{name} {half:.2g} or more{signs}", ~stop & big[..., i]),
                   (f"{name} under {half:.2g}{signs}", ~stop & ~big[..., i])]
    return groups


def by_command(row: dict, other: dict, commands, bounds) -> list[dict]:
    """Where ``row`` tracks closer or worse than ``other``: their per-piece errors (rows'
    ``per_piece``, ``per_piece_yaw``: each episode's RMSE under each command) paired piece by
    piece and grouped by the command (:func:`command_groups`). Each group: ``label``, ``n``
    pieces both scored, ``vel`` and ``yaw``, :func:`paired` over the pieces (the pieces of one
    episode taken as independent: a screen, not a test), and where the rows have them
    ``forward``: each row's mean forward speed minus the command there (m/s; + faster than
    asked). Empty where either row lacks per-piece errors."""
    if "per_piece" not in row or "per_piece" not in other:
        return []
    arr = lambda r, k: np.asarray([[np.nan if v is None else v for v in w] for w in r[k]], float)
    dv = arr(row, "per_piece") - arr(other, "per_piece")
    dw = arr(row, "per_piece_yaw") - arr(other, "per_piece_yaw")
    fwd = [arr(r, "per_piece_forward") if "per_piece_forward" in r else None
           for r in (row, other)]
    out = []
    for label, m in command_groups(commands, bounds):
        m = m & np.isfinite(dv) & np.isfinite(dw)
        g = dict(label=label, n=int(m.sum()), vel=paired(dv[m], np.zeros(m.sum())),
                 yaw=paired(dw[m], np.zeros(m.sum())))
        if fwd[0] is not None and fwd[1] is not None and m.any():  # which way each errs
            g["forward"] = [float(np.nanmean(f[m])) for f in fwd]
        out.append(g)
    return out


# what may differ between runs that share one selection: which candidates, and where it is written
_RESUMABLE_ANYWAY = ("candidates", "out")


def _plain(cfg: SelectConfig) -> dict:
    return json.loads(json.dumps(dataclasses.asdict(cfg)))  # tuples as JSON reads them back


def done_rows(cfg: SelectConfig) -> tuple[list[dict], dict | None]:
    """The rows already in ``OUT/selection.json`` that this run keeps (the candidates planned
    with the same settings, the same label, path and file content) and the policy's reference
    row there (None if none). A setting the saved table does not name (one added to the job
    since) counts at its default. Raises where ``OUT`` holds a selection made with other
    settings (the rows would not be paired with this run's)."""
    path = pathlib.Path(cfg.out) / "selection.json"
    if not path.is_file():
        return [], None
    table = json.loads(path.read_text())
    defaults = _plain(SelectConfig())
    mine = {k: v for k, v in _plain(cfg).items() if k not in _RESUMABLE_ANYWAY}
    theirs = {k: table["config"].get(k, defaults[k]) for k in mine}
    differ = sorted(k for k in mine if mine[k] != theirs[k])
    if differ:
        raise ValueError(f"{path} holds a selection made with other settings ({', '.join(differ)} "
                         f"differ): its episodes are not this run's; give another --out")
    wanted = set(cfg.pairs())
    return ([r for r in table["rows"] if (r["label"], r["path"]) in wanted  # (files exist)
             and r.get("sha256") == file_sha256(r["path"])], table.get("policy"))


def validation_commands(cfg: SelectConfig):
    """``(policy, env_cfg, starts [P], values [W, P, 3], keys [W])``: the planner's policy and
    its task, the validation episodes' command schedules -- a new command every ``change_s``,
    drawn from the policy's training distribution as the planner's value data are
    (:func:`stride_jax.control.planner_value.collect`) -- and each episode's planner key; the
    same for every run of ``cfg``'s seed (cheap: no model is loaded)."""
    policy, _, env_cfg = ppo.load_policy(cfg.policy)
    if env_cfg.robot != cfg.robot:
        raise ValueError(f"the policy {cfg.policy} drives {env_cfg.robot}, not {cfg.robot}")
    key_cmd, key_run = jax.random.split(jax.random.key(cfg.seed))
    starts, values = envs.command_schedules(env_cfg.commands, key_cmd, cfg.worlds,
                                            max(1, int(np.ceil(cfg.seconds / cfg.change_s))),
                                            cfg.change_s)
    return policy, env_cfg, starts, values, jax.random.split(key_run, cfg.worlds)


def validation_episodes(cfg: SelectConfig, policy, env_cfg, starts, progress=None,
                        recorder=None, record_every: int = 1):
    """``(sm, episodes)``: the robot and ``episodes(learned_params, values [W, P, 3], keys [W],
    plan=True)``, the validation episodes side by side (un-jitted; ``plan=False``: the policy
    alone) with the planner built as the closed loop builds it from ``cfg``'s flags.
    ``recorder(planning, planner, sm, mx) -> record`` (``mx``: the episodes' MJX model) adds
    :func:`stride_jax.control.episode.run_episode`'s ``record`` (every ``record_every``-th
    step): the episodes then return ``(trace, recorded)``. ``progress(seconds)`` is called with
    the time simulated, once per simulated second."""
    from mujoco import mjx

    sm = sim_model.load(cfg.robot)
    mx = mjx.put_model(sm.mj)
    slots = envs.contact_slots(mx)
    if cfg.model == "oracle":
        step_fn = episode_lib.mjx_step_fn(sm, mx)
    else:
        step_fn = episode_lib.learned_step_fn(cfg.model.partition("=")[2], sm, cfg.kernel,
                                              cfg.model_precision, cfg.model_substeps)
    error_params = None
    if cfg.error_model:
        from stride_jax.control import planner_value
        error_params = planner_value.load_error_model(cfg.error_model)
    sensors = seen_through(cfg.sensors, cfg.sensor_noise)
    n_steps = max(1, int(round(cfg.seconds / sm.robot.ctrl_dt)))
    every = max(1, int(round(1.0 / sm.robot.ctrl_dt)))  # a progress line per simulated second
    seconds = None if progress is None else (lambda steps: progress(int(steps) * sm.robot.ctrl_dt))

    def episodes(learned_params, values, keys, plan=True):
        planning = planning_lib.make_planning(cfg.planning, env_cfg, sm, step_fn, policy,
                                              learned_params, error_params=error_params)
        planner = None  # plan=False: the policy alone (the learned files unused)
        if plan:
            with jax.ensure_compile_time_eval():  # mppi.make checks its bounds eagerly
                planner = planning_lib.make_planner(
                    planning, planning_lib.mppi_config(cfg.mppi, cfg.planning, planning))
        record = recorder(planning, planner, sm, mx) if recorder is not None and plan else None
        return jax.vmap(lambda v, k: episode_lib.run_episode(
            sm, mx, slots, planning, planner, n_steps, starts, v, k, progress=seconds,
            progress_every=every, sensors=sensors, record=record,
            record_every=record_every))(values, keys)

    return sm, episodes


def run(cfg: SelectConfig, command: str = "", log=print) -> list[dict]:
    """Plans the validation episodes with every candidate not yet in ``OUT/selection.json``;
    writes ``selection.{json,md}`` after each."""
    code = code_version()  # read before the work, not when the table is written
    pairs = cfg.pairs()
    if not pairs:
        raise ValueError("candidates: give at least one LABEL=PATH (reward_value.msgpack)")
    for label, path in pairs:  # a missing file fails before any compile
        if not pathlib.Path(path).is_file():
            raise FileNotFoundError(f"candidate {label}: no learned reward/value file at {path}")
    rows, reference = done_rows(cfg)
    if rows:
        log(f"{cfg.out}: {', '.join(r['label'] for r in rows)} planned already; kept")
    if not cfg.policy_reference:
        reference = None
    out = pathlib.Path(cfg.out)

    def write(rows):
        table = dict(command=command, code=code, config=dataclasses.asdict(cfg), rows=rank(rows),
                     candidates=len(pairs), policy=reference, commands=commands,
                     command_bounds=bounds)
        out.mkdir(parents=True, exist_ok=True)
        atomic_write_text(out / "selection.json", json.dumps(table, indent=1))
        atomic_write_text(out / "selection.md", markdown(table))
        return table["rows"]

    def finish(rows):
        ranked = write(rows)
        log(f"best: {ranked[0]['label']}; wrote {out}")
        return ranked

    policy, env_cfg, starts, values, keys = validation_commands(cfg)
    # each episode's (forward, lateral, yaw) per change go into the table, to read where a
    # planner gains or loses against the policy
    commands = np.asarray(values).round(4).tolist()
    bounds = [np.asarray(b).tolist() for b in env_cfg.commands.bounds()]
    kept = {r["label"] for r in rows}
    todo = [(label, path) for label, path in pairs if label not in kept]
    if not todo and (reference is not None or not cfg.policy_reference):
        return finish(rows)
    now = {"label": "", "t0": 0.0}  # the running candidate, for the progress callback

    def progress(seconds):
        log(f"  {now['label']}: {seconds:.1f} of {cfg.seconds:g} s simulated "
            f"({time.monotonic() - now['t0']:.0f} s)")

    _, episodes = validation_episodes(cfg, policy, env_cfg, starts, progress)
    # the learned files are the argument: candidates of one structure share one compile
    episodes = jax.jit(episodes, static_argnames="plan")

    def score(label, params, plan=True):
        t0 = now["t0"] = time.monotonic()
        now["label"] = label
        trace = jax.block_until_ready(episodes(params, values, keys, plan=plan))
        worlds = [jax.tree.map(lambda x, i=i: x[i], trace) for i in range(cfg.worlds)]
        per = [episode_lib.metrics(w, cfg.settle_s) for w in worlds]
        pieces = [episode_lib.piece_errors(w, starts, cfg.settle_s) for w in worlds]
        plain = lambda a: [None if not np.isfinite(v) else float(v) for v in a]
        fell = [bool(m["fell"]) for m in per]
        up = [m["vel_rmse"] for m, f in zip(per, fell) if not f]
        row = dict(label=label, falls=sum(fell), worlds=cfg.worlds,
                   vel_rmse=float(np.mean(up)) if up else float("nan"),
                   per_world=[float(m["vel_rmse"]) for m in per], fell=fell,
                   per_piece=[plain(e["vel"]) for e in pieces],
                   per_piece_yaw=[plain(e["yaw"]) for e in pieces],
                   per_piece_forward=[plain(e["offset"][:, 0]) for e in pieces],
                   seconds=time.monotonic() - t0, code=code)  # a resumed table mixes runs
        log(f"{label}: velocity RMSE {row['vel_rmse']:.4f} m/s over {len(up)} worlds up, "
            f"{row['falls']} of {cfg.worlds} fell ({row['seconds']:.0f} s)")
        return row

    if cfg.policy_reference and reference is None:
        log(f"the policy alone: {cfg.worlds} episodes of {cfg.seconds:g} s side by side "
            "(a reference, not a candidate)")
        reference = score("policy", learned_lib.load(pairs[0][1], ensemble=True), plan=False)
    for label, path in todo:
        log(f"{label}: {cfg.worlds} episodes of {cfg.seconds:g} s side by side ({path})")
        rows.append(dict(score(label, learned_lib.load(path, ensemble=True)), path=path,
                         sha256=file_sha256(path)))
        if len(rows) < len(pairs):
            write(rows)  # after each candidate: a cut run keeps what it finished
    return finish(rows)


def markdown(table: dict) -> str:
    c = table["config"]
    lines = ["# Which learned reward and value to plan with: the closed loop on validation "
             "episodes", "", f"Command: `{table['command']}` (code {table['code']})", "",
             f"{c['worlds']} episodes of {c['seconds']} s on the nominal ground, a command drawn "
             f"from the policy's training distribution every {c['change_s']} s, the same draws "
             f"and planner keys for every candidate; planner model `{c['model']}`, policy "
             f"`{c['policy']}`. Velocity RMSE (m/s) over the episodes that stayed up; against "
             "the best: the mean paired difference with its 90% t-interval over the episodes "
             "both kept up." + ("" if len(table["rows"]) >= table.get("candidates", 0) else
                                 f" **{len(table['rows'])} of {table['candidates']} candidates "
                                 "planned so far.**"), "",
             "| rank | candidate | falls | velocity RMSE | minus the best | file |",
             "|---:|---|---:|---:|---|---|"]
    for i, r in enumerate(table["rows"], 1):
        v = r["vs_best"]
        vs = "-" if v is None and i == 1 else interval(v)
        lines.append(f"| {i} | {r['label']} | {r['falls']} of {r['worlds']} | "
                     f"{r['vel_rmse']:.4f} | {vs} | `{r['path']}` |")
    rows = table["rows"]
    ref = table.get("policy")
    if ref is not None:
        v = versus(rows[0], ref)
        lines += ["", f"The policy alone on the same episodes (a reference, not a candidate): "
                  f"{ref['vel_rmse']:.4f}, {ref['falls']} of {ref['worlds']} fell; the best "
                  f"candidate minus the policy: " + ("n/a" if v is None else
                  f"{interval(v)} over {v['n']} episodes") + "."]
        where = by_command(rows[0], ref, table.get("commands", []),
                           table.get("command_bounds")) if table.get("command_bounds") else []
        if where:
            lines += ["", f"Where {rows[0]['label']} and the policy differ: each episode's "
                      "error under each command (after the settling time), the best minus the "
                      "policy, grouped by the command (90% t-intervals over the pieces, the "
                      "pieces of one episode taken as independent: a screen).", "",
                      "| commands | pieces | velocity RMSE (m/s) | yaw-rate RMSE (rad/s) | "
                      "forward speed minus the command: best, policy (m/s) |",
                      "|---|---:|---|---|---|"]
            lines += [f"| {g['label']} | {g['n']} | {interval(g['vel'])} | {interval(g['yaw'])} | "
                      + (", ".join(f"{x:+.3f}" for x in g["forward"]) if "forward" in g
                         else "n/a") + " |" for g in where]
    # no interval (identical errors, or under two episodes both kept up) tells nothing apart
    ties = [r["label"] for r in rows[1:] if r["falls"] == rows[0]["falls"]
            and (r["vs_best"] is None or r["vs_best"]["lo"] <= 0)]
    lines += ["", f"Not told apart from the best ({rows[0]['label']}): "
              f"{', '.join(ties) if ties else 'none'}. The rank among these is not established "
              "by these episodes; more worlds, or a reason outside this table, decide it."]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    config.config_main("python -m stride_jax.jobs.select_learned", SelectConfig, PRESETS, run,
                       argv, __doc__.split("\n")[0])


if __name__ == "__main__":
    stride_jax.set_xla_flags()  # before JAX starts: small CPUs deadlock without
    main()
