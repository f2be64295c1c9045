"""MPPI in closed loop on the MJX Go1 or G1: any dynamics model plans, the simulator acts.

Each control period (20 ms) the planner (:mod:`stride_jax.control.mppi`) sees the simulator's
state and the current command, plans through its model, and the first action is simulated in MJX
with the scenario's ground. Planner models:

* ``oracle``: the scenario's own MJX model (slope, friction, softness, terrain included);
* ``nominal``: MJX with the nominal flat ground the robot was designed and trained on;
* ``policy``: no planner -- the PPO policy acting alone (a baseline);
* ``NAME=RUN``: a trained dynamics model of the one interface (``stride_jax.dynamics.load``;
  STRIDE, DeLaN, ONN ...), e.g. ``stride=runs/go1/stride``.

One episode (:func:`stride_jax.control.episode.run_episode`), its metrics and the planner's
models are the library's; this job runs every (scenario, model) pair of a
:class:`ClosedLoopConfig` and writes the table, traces and plots (``stride closed-loop``,
``python -m stride_jax.jobs.closed_loop``, ``experiments/closed_loop.py``).

The planner's view of the task (:mod:`stride_jax.control.planning`): its state is ``(q, command,
gait clock, latched gait)``, so one jitted planner follows command changes; its action is a
joint-target offset from home (with ``gait``, a residual on the Go1 gait reference plus the gait
parameters, optimised jointly); its cost is the environment's state reward terms, negated, plus a
tracking term and ``planning.fall_cost`` per step fallen, or (``learned``) the learned reward and value. A
PPO run can add ``policy_samples`` candidates. Offset-free planning in the policy's command space
(``planning.observer_gain``, ``mppi.family_samples``, ``planning.learned_track_weight``;
:mod:`stride_jax.control.planning`) is how issue 19's runs plan (``docs/control.md``).

Scenarios (:mod:`stride_jax.control.scenarios`): velocity step 0 -> 2 m/s, sudden command
changes, a 20 degree slope (from the first step, or ``tilt``: built up over two seconds), low
friction, soft contacts, rough terrain, pushes. The gait study lives in
:mod:`stride_jax.jobs.gait_study`. Reported per (scenario, model): tracking RMSE of the
base-frame velocity (xy) and yaw rate while
upright, falls, and planning time per step.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import pathlib
import statistics
import time
from typing import Callable, ClassVar

import jax
import jax.numpy as jnp
import numpy as np
from mujoco import mjx

import stride_jax
from stride_jax import config
from stride_jax.control import envs
# The library's episode, metrics and planner models, and the scenarios (re-exported: the job's
# callers and tests take them from here).
from stride_jax.control.episode import (PRECISIONS, Trace, World,  # noqa: F401
                                        continue_episode, controller_period, learned_model,
                                        learned_step, learned_step_fn, metrics, mjx_step_fn,
                                        run_episode, scenario_world, start_episode)
from stride_jax.control.mppi import MPPIConfig
from stride_jax.control.planning import (PlanningConfig, latency_steps, make_planner,
                                         make_planning, mppi_config)
from stride_jax.control.scenarios import (SCENARIOS, WALK, Scenario, command_at,  # noqa: F401
                                          payload_body, push_schedule, scenario_model, schedule,
                                          tilt_schedule)
from stride_jax.io import atomic_write, atomic_write_text, code_version
from stride_jax.jobs.headline import check_entries
from stride_jax.sim import model as sim_model
from stride_jax.sim.sensors import SensorNoise, seen_through
from stride_jax.timing import wall_times


# ---------------------------------------------------------------------------------------------
# The configuration.


@dataclasses.dataclass(frozen=True)
class ClosedLoopConfig:
    """Closed-loop runs.

    Attributes:
      robot: ``go1`` or ``g1`` (the policy and the learned models must be of it).
      models: comma-separated planner models (``oracle``, ``nominal``, ``policy``, ``NAME=RUN``).
      scenarios: comma-separated names of :data:`SCENARIOS`.
      seconds: override every scenario's duration (0: keep).
      slope_deg: override the slope of the scenarios that have one (0: keep; their names get
        the angle, ``tilt10``).
      rough_cm: override the bump height of the rough-ground scenarios (cm; 0: keep; their
        names get the height, ``rough2``).
      push_scale: scale the velocity change of every push of the scenarios that push (0: keep;
        their names get the factor, ``push3x``).
      friction: override the friction scale of the scenarios with a lowered friction (0: keep;
        their names get the value, ``low_friction0.15``).
      payload: override the payload of the scenarios that carry one (a fraction of the robot's
        mass, on its base or ``payload_body``; 0: keep; their names get the fraction,
        ``payload0.4``).
      payload_body: the body that carries the payload of the scenarios that carry one, by name
        ("": keep, the base body; their names get it, ``payload_on_torso_link``).
      mppi: the planner's settings (``--mppi.samples``, ``--mppi.horizon``, ...; the older flat
        flags ``--samples``, ``--horizon``, ``--policy-samples`` ... still answer). Its
        ``noise_std`` is set from ``planning.noise_std`` (and ``planning.gait_noise``), its
        ``policy_samples`` dropped to 0 without a policy.
      planning: the task side of the planner (:class:`~stride_jax.control.planning.PlanningConfig`:
        ``--planning.noise-std``, ``--planning.prior-noise-std``, ``--planning.plan-range``,
        ``--planning.gait``, ``--planning.gait-noise``, ``--planning.value-weight``,
        ``--planning.fall-cost``, ``--planning.track-weight``; the older flat flags
        ``--noise-std``, ``--gait`` ... still answer).
      policy: PPO run folder supplying candidates (and the ``policy`` model); "" for none.
      learned: learned reward/value file (``reward_value.msgpack``); "" for the analytic cost.
      error_model: a learned one-step error model of the planner's dynamics model
        (``error_model.msgpack`` of :mod:`stride_jax.control.planner_value`), used with
        ``--mppi.error-bound``/``--mppi.error-weight``; "" for none.
      kernel: how learned structured models run their networks (``xla``; ``pallas`` or
        ``pallas-bf16``: fused kernels on GPUs, ``stride_jax.dynamics.fused``;
        ``pallas-step[-bf16]``: STRIDE's whole step as one kernel where it applies).
      model_precision: the float32 matrix products of the learned models' steps (planner and
        observer): "" leaves JAX's default, which on a recent NVIDIA GPU multiplies in TF32
        (10-bit mantissas); ``highest`` multiplies in full float32, as a CPU always does and as
        the simulator's physics here always runs (``rollout_mjx.PRECISION``).
      settle_s: tracking errors are counted from this long after each command change (s).
      govern: a command governor: the controller (policy and planner) sees each command clipped
        to the ranges its environment's policy was trained on (``envs`` commands: forward,
        lateral, yaw), as a robot's operator interface would saturate it; the metrics still
        compare with the command asked for, so they count what the governor gives up.
      sense_gravity: the policy and the planner observe the simulation's gravity direction, as
        an IMU senses a real slope (the ``slope`` and ``tilt`` scenarios tilt gravity under a
        level floor); ``--no-sense-gravity``: world down, as every run before session 46 (a run
        that kept no such key is read so). Flat scenarios are the same either way.
      out: results folder (``closed_loop.json``/``.md`` and plots).
      progress_s: log the episode's progress every this many simulated seconds (0: only when
        a pair finishes).
      chunk_s: run each episode in chunks of this many simulated seconds, saving its state and
        trace after each (``OUT/partial/``, atomically): a run killed mid-episode (a time limit,
        a lost machine) resumes at its last chunk when called again with the same settings, so
        it loses at most one chunk (settings that only time the controller may differ; the
        state stays until the pair's rows are written, so one killed after its last chunk
        resumes at its end); a state saved with other settings or code is not resumed: the log
        says which settings differ and the state is kept beside as ``<pair>.stale<k>.npz``,
        never overwritten.
        0: one program per episode, nothing saved before its row.
        The same trace either way, to float rounding (the chunks run the same step, one after
        another, compiled as another program: measured 1e-7 relative on the CPU).
      seed: planner key and terrain seed.
      episodes: episodes of each (scenario, model) pair side by side in one program (vmapped
        over the planner's key): seeds ``seed``, ``seed + 1``, ... draw the planner's noise, the
        residual's latents and the observer's draws; the ground (rough terrain) stays
        ``seed``'s. One row per episode (``seed``, ``episode``); ``ms_per_step`` is then the
        wall time of one control step of all of them together. On a GPU several episodes cost
        little more than one (a planner's step is latency-bound), so this is how a pair is
        measured over draws.
      latency_auto: each planner runs late by its own controller's time on this machine: per
        pair, its controller is timed on time first (``controller_repeats``), and
        ``planning.latency_s`` is set to the longest of those times (a real-time loop budgets
        its worst case; rows: ``latency_auto_ms``, ``latency_steps``), so
        planners of different speeds (ONN, STRIDE, the oracle) are compared as a robot with this
        computer would run them. Compensation and feedback as ``planning`` says.
      model_substeps: the learned structured models (STRIDE, DeLaN, LNN + diffusion) integrate
        each control period in this many substeps in the planner and the observer
        (``models.with_substeps``: the same accelerations, integrated coarser or finer); 0: as
        each was trained (Go1's and G1's: 5 of 4 ms). Next-observation models are unchanged.
      controller_repeats: time the controller's own computation per control period this many
        times after the episode (``controller_ms`` in each row, the median, and
        ``controller_ms_max`` the longest; one episode's, with
        no simulated world: what a robot's computer must fit in 20 ms, where ``ms_per_step``
        also counts the simulation and side-by-side episodes). 0: not timed.
      sensor_noise: the controller (policy, planner, its observer and integral action) sees
        the state through a real robot's sensors and state estimator, ``sensors`` with every
        standard deviation times this factor (``SensorNoise.scaled``; a fresh draw each period,
        the episode's key): 1 is a well-instrumented robot, larger a worse estimator. 0: the
        exact state (every run before session 81). Scenario names get the factor
        (``rough_noise3``); rows record it.
      sensors: the sensors' terms (``--sensors.linvel-std``, ``--sensors.gyro-std``, ...;
        :class:`stride_jax.sim.sensors.SensorNoise`), used where ``sensor_noise`` > 0.
      together: the scenarios whose worlds differ in values alone (friction, softness, gravity,
        a payload's mass, pushes, commands; not rough ground's heightfield) run side by side in
        one program per model, each episode in its own world: a GPU fills with scenarios x
        ``episodes`` episodes instead of one scenario's. The same episodes as run apart, in a
        program of another batch shape, which rounds otherwise (tested: rows to 1e-5 over a
        few steps); a closed loop amplifies rounding as it goes (a falling Go1 under a tiny CPU
        planner: 2e-5 m/s apart after 7 steps, 0.4 m/s after 40), so over seconds a row is
        another draw of the same planner. ``ms_per_step`` is then the
        wall time of a control step of them all (``side_by_side`` says how many,
        ``scenarios_together`` which), ``controller_ms`` one episode's controller as ever.
    """

    robot: str = "go1"
    models: str = "oracle,nominal"
    scenarios: str = "step,changes,slope,low_friction,soft,rough"
    seconds: float = 0.0
    slope_deg: float = 0.0
    rough_cm: float = 0.0
    push_scale: float = 0.0
    friction: float = 0.0
    payload: float = 0.0
    payload_body: str = ""
    mppi: MPPIConfig = MPPIConfig()
    planning: PlanningConfig = PlanningConfig()
    policy: str = ""
    learned: str = ""
    error_model: str = ""
    kernel: str = "xla"
    model_precision: str = ""
    settle_s: float = 0.5
    progress_s: float = 1.0
    chunk_s: float = 0.0
    govern: bool = False
    sense_gravity: bool = True
    out: str = "results/closed_loop"
    seed: int = 0
    episodes: int = 1
    controller_repeats: int = 10
    latency_auto: bool = False
    model_substeps: int = 0
    sensor_noise: float = 0.0
    sensors: SensorNoise = SensorNoise()
    together: bool = False

    def __post_init__(self):
        if self.episodes < 1:
            raise ValueError(f"--episodes is {self.episodes}: it must be >= 1")
        if self.latency_auto and (self.planning.latency_s or not self.controller_repeats):
            raise ValueError("--latency-auto sets each planner's latency to its measured time: "
                             "it needs --controller-repeats >= 1 and no --planning.latency-s")
        if self.model_substeps < 0:
            raise ValueError(f"--model-substeps is {self.model_substeps}: it must be >= 0 (0: "
                             "as each model was trained)")
        if self.controller_repeats < 0:
            raise ValueError(f"--controller-repeats is {self.controller_repeats}: it must be "
                             ">= 0 (0: the controller is not timed)")
        if self.chunk_s < 0:
            raise ValueError(f"--chunk-s is {self.chunk_s}: it must be >= 0 (0: no chunks)")
        if self.model_precision not in PRECISIONS:
            raise ValueError(f"--model-precision is {self.model_precision!r}: use one of "
                             f"{', '.join(repr(p) for p in PRECISIONS)}")
        seen_through(self.sensors, self.sensor_noise)  # a clear error for a bad pair
        for field in ("seconds", "slope_deg", "rough_cm", "push_scale", "friction", "payload"):
            if getattr(self, field) < 0:
                raise ValueError(f"--{field.replace('_', '-')} is {getattr(self, field)}: it must be >= 0 "
                                 "(0 keeps the scenario's own)")

    # The flat flags of earlier commands (recorded in results/) still answer.
    FLAG_ALIASES: ClassVar[dict[str, str]] = {
        **{f"mppi.{name}": "--" + name.replace("_", "-")
           for name in ("samples", "horizon", "iterations", "temperature", "smoothing",
                        "policy_samples", "policy_noise", "risk_draws", "risk", "risk_alpha",
                        "risk_weight")},
        **{f"planning.{f.name}": "--" + f.name.replace("_", "-")
           for f in dataclasses.fields(PlanningConfig)}}


PRESETS = {
    "tiny": ClosedLoopConfig(models="oracle", scenarios="step", seconds=0.2,
                             mppi=MPPIConfig(samples=8, horizon=3), settle_s=0.0,
                             out="results/closed_loop/tiny"),
    "default": ClosedLoopConfig(),
    "gpu": ClosedLoopConfig(mppi=MPPIConfig(samples=1024, horizon=20),
                            out="results/closed_loop/gpu"),
}


# ---------------------------------------------------------------------------------------------
# The job: every (scenario, model) pair, the table and the plots.


def _parse_models(spec: str) -> list[tuple[str, str]]:
    out = []
    for item in [s for s in spec.split(",") if s]:
        name, _, run = item.partition("=")
        if not run and name not in ("oracle", "nominal", "policy"):
            raise ValueError(f"unknown model {item!r}: use oracle, nominal, policy or NAME=RUN")
        out.append((name, run))
    return out


def run(cfg: ClosedLoopConfig, command: str = "", log=print) -> list[dict]:
    """Every (scenario, model) pair of ``cfg``; writes ``closed_loop.json``/``.md``, traces and
    plots to ``cfg.out`` after each pair, and skips pairs already there (resumable)."""
    from stride_jax.control import learned as learned_lib, ppo
    from stride_jax.dynamics import checkpoint, fused, models as dyn_models

    fused.kernel_dtype(cfg.kernel)  # a clear error for an unknown choice, before any work
    code = code_version()  # the code this process runs: read now, not when a row is written
    sm = sim_model.load(cfg.robot)
    names = [s for s in cfg.scenarios.split(",") if s]
    unknown = [s for s in names if s not in SCENARIOS]
    if unknown:
        raise ValueError(f"unknown scenarios {unknown}; known: {', '.join(SCENARIOS)}")
    scenarios = [scenario(cfg, s) for s in names]
    for sc in scenarios:  # a payload's body named wrong fails before any model loads
        if sc.payload:
            payload_body(sm, sc)
    models = _parse_models(cfg.models)
    ppo_policy, env_cfg = None, envs.config(cfg.robot)
    if cfg.policy:
        ppo_policy, _, env_cfg = ppo.load_policy(cfg.policy)
        if env_cfg.robot != cfg.robot:
            raise ValueError(f"the policy {cfg.policy} drives {env_cfg.robot}, not {cfg.robot}")
    learned_params = learned_lib.load(cfg.learned, ensemble=True) if cfg.learned else None
    error_params = None
    if cfg.error_model:
        from stride_jax.control import planner_value
        error_params = planner_value.load_error_model(cfg.error_model)
    out = pathlib.Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "closed_loop.json"
    rows = json.loads(path.read_text())["rows"] if path.is_file() else []
    done = {(r["scenario"], r["model"], r.get("seed", cfg.seed)) for r in rows}
    seeds = list(range(cfg.seed, cfg.seed + cfg.episodes))
    batched = cfg.episodes > 1
    mx_nominal = mjx.put_model(sm.mj)
    # trained models: (model, params); the params and the data scales are the episode's
    # argument, so the runs of one kind of model (trained seeds of one recipe) share one
    # compiled episode
    learned = {name: learned_model(run_dir, sm, cfg.kernel) for name, run_dir in models if run_dir}
    if cfg.model_substeps:
        coarse = [n for n, (m, _) in learned.items() if dyn_models.has_substeps(m)]
        for n in coarse:
            m, params = learned[n]
            learned[n] = (dyn_models.with_substeps(m, cfg.model_substeps), params)
        log(f"--model-substeps {cfg.model_substeps}: {', '.join(coarse) or 'no model'} "
            "integrate each control period in as many substeps"
            + (f"; {', '.join(n for n in learned if n not in coarse)} predict the period at once"
               if len(coarse) < len(learned) else ""))
    kind = {name: ("learned", checkpoint.program_sha256(m)) for name, (m, _) in learned.items()}
    context = [n for n, (m, _) in learned.items() if m.config.gravity_context]
    if context and not cfg.planning.model_gravity:
        log(f"{', '.join(context)}: trained with gravity_context (on sloped data), here told "
            "world down; --planning.model-gravity tells them the sensed gravity")
    if cfg.planning.model_gravity:
        told = [n for n, (m, _) in learned.items() if dyn_models.takes_gravity(m)]
        untold = [n for n in learned if n not in told]
        log("--planning.model-gravity: the sensed gravity reaches "
            + (", ".join(told) or "no model")
            + (f"; {', '.join(untold)} cannot take it (run as trained)" if untold else ""))
    if any(name == "policy" for name, _ in models) and ppo_policy is None:
        raise ValueError("model 'policy' needs --policy RUN")
    compiled = {}  # one executable per (kind of model, episode length, model structures)
    sensors = seen_through(cfg.sensors, cfg.sensor_noise)
    limits = env_cfg.commands.bounds() if cfg.govern else None
    every = max(1, int(round(cfg.progress_s / sm.robot.ctrl_dt))) if cfg.progress_s > 0 else 0
    now = {"label": "", "t0": 0.0, "n": 1}  # the running pair, for the progress callback

    def progress(steps):
        if int(steps) > now["n"]:  # a last chunk's steps past the episode's end (dropped)
            return
        dt, wall = sm.robot.ctrl_dt, time.perf_counter() - now["t0"]
        log(f"  {now['label']}: {int(steps) * dt:.1f} of {now['n'] * dt:.1f} s simulated "
            f"({wall:.0f} s)")

    # each model's planning settings: cfg.planning's, with --latency-auto its latency set to its
    # controller's measured time (per pair, before its episode is compiled)
    plan_cfg: dict[str, PlanningConfig] = {}

    def parts(name, mx_plan, learned_args):
        """The planner's view of the task and the planner for model ``name``."""
        if name in learned:
            params, scales = learned_args
            step_fn = learned_step(checkpoint.with_scales(learned[name][0], scales), params,
                                   cfg.model_precision)
        else:
            step_fn = mjx_step_fn(sm, mx_plan)
        pcfg = plan_cfg.get(name, cfg.planning)
        planning = make_planning(pcfg, env_cfg, sm, step_fn, ppo_policy, learned_params,
                                 error_params=error_params if name in learned
                                 else None)  # the simulator has no model error
        planner = None
        if name != "policy":
            with jax.ensure_compile_time_eval():  # mppi.make checks its bounds eagerly
                planner = make_planner(planning, mppi_config(cfg.mppi, pcfg, planning))
        return planning, planner

    def episode_fn(name, n_steps, slots, sm_sim, batched, chunk=0, axes=EPISODES_AXES):
        """The jitted episode; with ``chunk`` steps, ``(start, continue)``: the episode's first
        state, and ``chunk`` steps from a state at a step given at run time. ``batched``: vmapped
        over the arguments ``axes`` marks (:data:`EPISODES_AXES`: the key alone, one world's
        draws; :func:`_world_axes`: scenarios side by side too)."""
        episode_kw = dict(limits=limits, progress=progress if every else None,
                          progress_every=every or 1, sense_gravity=cfg.sense_gravity,
                          sensors=sensors)

        def episode(mx_sim, mx_plan, learned_args, starts, values, pushes, tilt, key):
            planning, planner = parts(name, mx_plan, learned_args)
            return run_episode(sm_sim, mx_sim, slots, planning, planner, n_steps, starts, values,
                               key, pushes=pushes, tilt=tilt, **episode_kw)

        def start(mx_sim, mx_plan, learned_args, starts, values, pushes, tilt, key):
            return start_episode(sm_sim, mx_sim, *parts(name, mx_plan, learned_args), key)

        def resume(carry, first, mx_sim, mx_plan, learned_args, starts, values, pushes, tilt, key):
            return continue_episode(
                sm_sim, mx_sim, slots, *parts(name, mx_plan, learned_args), carry, first, chunk,
                starts, values, key, pushes=pushes, tilt=tilt, **episode_kw)

        if not chunk:
            # episodes side by side: only the key differs
            return jax.jit(jax.vmap(episode, in_axes=axes) if batched else episode)
        if batched:
            start = jax.vmap(start, in_axes=axes)
            resume = jax.vmap(resume, in_axes=(0, None) + axes)
        return jax.jit(start), jax.jit(resume)

    timed = {}  # the controller's own period, compiled once per compiled episode

    def controller_ms(name, sm_sim, one, sig) -> tuple[float, float, float]:
        """``(median ms, longest ms, compile s)`` of the controller's own computation in one
        control period (:func:`controller_period`: one episode's, from its start, the planner's
        state carried over ``cfg.controller_repeats`` periods): what a robot's computer must fit
        in a period."""
        t0 = time.perf_counter()
        if sig not in timed:
            def begin(mx_sim, mx_plan, learned_args, key):
                return start_episode(sm_sim, mx_sim, *parts(name, mx_plan, learned_args), key)

            def period(carry, mx_sim, mx_plan, learned_args, key):
                return controller_period(sm_sim, mx_sim, *parts(name, mx_plan, learned_args),
                                         carry, key)
            timed[sig] = (jax.jit(begin), jax.jit(period))
        begin, period = timed[sig]
        mx_sim, mx_plan, learned_args, key = one  # one episode's world, model and key
        carry = [begin(mx_sim, mx_plan, learned_args, key)]

        def once():
            _, ps, _ = jax.block_until_ready(period(carry[0], mx_sim, mx_plan, learned_args, key))
            carry[0] = (carry[0][0], ps, *carry[0][2:])  # warm-started as in the episode
        once()  # compiled
        compile_s = time.perf_counter() - t0
        times = wall_times(once, cfg.controller_repeats, warm_up=False)  # warm: once() above
        return 1e3 * statistics.median(times), 1e3 * max(times), compile_s

    for group in _groups(sm, scenarios, cfg.seed, cfg.together):
        world = group[0][1]  # the group's worlds differ in values only (_groups)
        n_steps, sm_sim, slots = world.n_steps, world.sm, world.slots
        label = "+".join(sc.name for sc, _ in group)
        together = len(group) > 1
        stacks = {}  # the worlds stacked along the batch, per episode list (once for all models)
        for name, run_dir in models:
            members = [(sc, w, seed) for sc, w in group for seed in seeds
                       if (sc.name, name, seed) not in done]
            if not members:
                continue
            todo = [seed for *_, seed in members]
            batch = batched or together
            keys = (jax.vmap(jax.random.key)(jnp.asarray(todo)) if batch
                    else jax.random.key(todo[0]))
            learned_args = ((learned[name][1], learned[name][0].scales) if name in learned
                            else ())
            oracle = name == "oracle"
            if together:  # each episode its own world: the worlds stacked along the batch
                which = tuple(sc.name for sc, _, _ in members)
                if which not in stacks:
                    stacks[which] = [jax.tree.map(lambda *xs: jnp.stack(xs),
                                                  *[getattr(w, f) for _, w, _ in members])
                                     for f in ("mx", "starts", "values", "pushes", "tilt")]
                mxs, starts, values, pushes, tilt = stacks[which]
                args = (mxs, mxs if oracle else mx_nominal, learned_args, starts, values, pushes,
                        tilt, keys)
                axes = _world_axes(oracle)
            else:
                args = (world.mx, world.mx if oracle else mx_nominal, learned_args,
                        world.starts, world.values, world.pushes, world.tilt, keys)
                axes = EPISODES_AXES
            first = members[0][1].mx  # one episode's arguments, for the controller's timing
            one = (first, first if oracle else mx_nominal, learned_args, jax.random.key(todo[0]))
            chunk = _chunk_steps(cfg.chunk_s, sm.robot.ctrl_dt, n_steps)
            planned = name != "policy"
            sig = (kind.get(name, name), n_steps, tuple(slots[0]), sm_sim.geom_foot.tobytes(),
                   jax.tree.structure(args[:3]), len(todo) if batch else 0, chunk)
            if together:
                sig += (axes,)
            plan_cfg[name], auto_ms = cfg.planning, None
            if cfg.latency_auto and planned:  # late by its own (longest) time on this machine
                median_ms, auto_ms, auto_compile_s = controller_ms(name, sm_sim, one,
                                                                   sig + (0,))
                plan_cfg[name] = dataclasses.replace(cfg.planning, latency_s=auto_ms / 1e3)
                log(f"  {label} {name}: --latency-auto: its controller takes {median_ms:.1f} "
                    f"ms on time (median; longest {auto_ms:.1f}; compile {auto_compile_s:.0f} "
                    f"s), so its plans act {latency_steps(plan_cfg[name], sm.robot.ctrl_dt)} "
                    "period(s) late")
            lat = latency_steps(plan_cfg[name], sm.robot.ctrl_dt) if planned else 0
            sig += (lat,)
            t0 = time.perf_counter()
            if sig not in compiled:
                if every:
                    log(f"  {label} {name}: compiling")
                fn = episode_fn(name, n_steps, slots, sm_sim, batch, chunk, axes)
                compiled[sig] = (fn.lower(*args).compile() if not chunk else
                                 (fn[0].lower(*args).compile(),
                                  fn[1].lower(jax.eval_shape(fn[0], *args), 0, *args).compile()))
            compile_s = time.perf_counter() - t0
            t0 = time.perf_counter()
            now.update(label=f"{label} {name}", t0=t0, n=n_steps)
            if chunk:
                partial = out / "partial" / f"{label}_{name}.npz"
                # the pair and the settings its episodes depend on (not where they are written,
                # nor the run's other pairs: a call naming fewer models resumes as well)
                settings = {k: v for k, v in dataclasses.asdict(cfg).items() if k not in _PER_RUN}
                ident = dict(settings=settings, model=name, run=run_dir, seeds=todo,
                             chunk=chunk, n_steps=n_steps, latency_steps=lat)
                if together:  # which scenario each episode walks
                    ident["scenarios"] = [sc.name for sc, _, _ in members]
                traces, run_s = _chunked(compiled[sig], args, n_steps, chunk, batch, partial,
                                         json.dumps(ident, sort_keys=True, default=str), now,
                                         log)
            else:
                traces = jax.block_until_ready(compiled[sig](*args))
                run_s = time.perf_counter() - t0
                traces = jax.tree.map(np.asarray, traces)  # one copy to the host for all episodes
            ctl_ms = ctl_max = None
            if cfg.controller_repeats:
                ctl_ms, ctl_max, ctl_compile_s = controller_ms(name, sm_sim, one, sig)
                budget_ms = 1e3 * sm.robot.ctrl_dt * max(lat, 1)
                log(f"  {label} {name}: the controller's own period {ctl_ms:.1f} ms "
                    f"(median of {cfg.controller_repeats}, longest {ctl_max:.1f}; compile "
                    f"{ctl_compile_s:.0f} s)"
                    + ("" if ctl_max <= budget_ms else
                       f": the longest over the {budget_ms:.0f} ms of its {max(lat, 1)} "
                       "period(s), so a robot could not run it so" + ("" if lat else
                                                 " (--planning.latency-s runs it late)")))
            for i, (sc, _, seed) in enumerate(members):
                trace = jax.tree.map(lambda x: x[i], traces) if batch else traces
                episode = seed - cfg.seed
                row = dict(scenario=sc.name, model=name, run=run_dir or None,
                           **metrics(trace, cfg.settle_s),
                           ms_per_step=1e3 * run_s / n_steps, controller_ms=ctl_ms,
                           controller_ms_max=ctl_max,
                           compile_s=compile_s,
                           steps=n_steps, K=cfg.mppi.samples if planned else None,
                           H=cfg.mppi.horizon if planned else None,
                           latency_steps=lat if planned else None,
                           **({"latency_auto_ms": auto_ms} if auto_ms is not None else {}),
                           **({"sensor_noise": cfg.sensor_noise} if sensors else {}),
                           seed=seed,
                           episode=episode, side_by_side=len(todo) if batch else 1,
                           **({"scenarios_together": label} if together else {}))
                rows.append(row)
                np.savez_compressed(out / trace_name(sc.name, name, episode, seed),
                                    **trace._asdict())
                log(f"{sc.name:>12} {name:>8}{f' seed {seed}' if batch else ''}: vel RMSE "
                    f"{row['vel_rmse']:.3f} m/s, yaw RMSE {row['yaw_rmse']:.3f} rad/s, fell "
                    f"{row['fell']}, {row['ms_per_step']:.1f} ms/step (compile {compile_s:.0f} s)")
            write(rows, cfg, command, out, code)
            if chunk:
                _drop_state(partial)
    plot(out, rows)
    return rows


# the episode program's batch axes over (mx_sim, mx_plan, learned_args, starts, values, pushes,
# tilt, key): one world's episodes side by side differ in their key alone
EPISODES_AXES = (None,) * 7 + (0,)


def _world_axes(oracle: bool) -> tuple:
    """The batch axes of episodes in several worlds side by side (``--together``): each its own
    simulated model and schedules; the planner's model too for the oracle, which plans through
    its episode's world."""
    return (0, 0 if oracle else None, None, 0, 0, 0, 0, 0)


def _groups(sm: sim_model.SimModel, scenarios: list[Scenario], seed: int, together: bool):
    """The scenarios in the order run, as groups of ``(scenario, World)``: one each, or with
    ``together`` those whose worlds share one compiled episode (the same length, contact slots,
    feet and MJX model structure, so that they differ in values alone: friction, softness,
    gravity, masses, pushes, commands) in one group, in the order of their first scenario.
    Rough ground (a heightfield, another structure) stays apart."""
    if not together:
        for sc in scenarios:
            yield [(sc, scenario_world(sm, sc, seed))]
        return
    def shapes(tree) -> tuple:
        return tuple((np.shape(x), str(getattr(x, "dtype", type(x).__name__)))
                     for x in jax.tree.leaves(tree))

    groups: dict[tuple, list] = {}
    for sc in scenarios:
        w = scenario_world(sm, sc, seed)
        key = (w.n_steps, tuple(np.asarray(x).tobytes() for x in w.slots),
               w.sm.geom_foot.tobytes(), jax.tree.structure(w.mx), shapes(w.mx),
               shapes((w.starts, w.values, w.pushes, w.tilt)))
        groups.setdefault(key, []).append((sc, w))
    yield from groups.values()


def _chunk_steps(chunk_s: float, dt: float, n_steps: int) -> int:
    """Control steps per chunk for ``--chunk-s`` (0: none): chunks of equal length, as few as
    ``chunk_s`` allows (the last may run past the episode's end; its extra steps are dropped)."""
    if chunk_s <= 0:
        return 0
    n_chunks = -(-n_steps // max(1, int(round(chunk_s / dt))))
    return -(-n_steps // n_chunks)


def _save_state(path: pathlib.Path, carry, traces: list, steps: int, run_s: float,
                ident: str) -> None:
    """A chunked episode's state after ``steps`` control steps, atomically: its carry (typed
    PRNG keys as their data), the traces (:class:`Trace`) of the chunks so far, and what
    identifies the run."""
    leaves = jax.tree.leaves(carry)
    keys = [i for i, x in enumerate(leaves) if jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key)]
    arrays = {f"carry{i}": np.asarray(jax.random.key_data(x) if i in keys else x)
              for i, x in enumerate(leaves)}
    for k, chunk in enumerate(traces):
        arrays.update({f"trace{k}_{f}": x for f, x in chunk._asdict().items()})
    meta = dict(ident=ident, steps=steps, run_s=run_s, keys=keys, chunks=len(traces))
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, lambda f: np.savez(f, meta=np.array(json.dumps(meta)), **arrays))


def _load_state(path: pathlib.Path, carry_like, ident: str):
    """``(carry, traces, steps, run_s)`` saved by :func:`_save_state` for the run ``ident``;
    None where there is none; where there is another run's, or another episode state's (other
    code), a line saying why it is not this run's (the caller sets it aside, not resumed)."""
    if not path.is_file():
        return None
    with np.load(path) as z:
        meta = json.loads(str(z["meta"]))
        leaves, treedef = jax.tree.flatten(carry_like)
        shapes = [z[f"carry{i}"].shape if f"carry{i}" in z.files else None
                  for i in range(len(leaves))]
        want = [jax.random.key_data(x).shape if i in meta["keys"] else x.shape
                for i, x in enumerate(leaves)]
        if meta["ident"] != ident and not _same_run(meta["ident"], ident):
            return _ident_difference(meta["ident"], ident)
        if shapes != want or f"carry{len(leaves)}" in z.files:
            n = sum(f.startswith("carry") for f in z.files)
            return (f"its episode state has {n} arrays of other shapes than this code's "
                    f"{len(leaves)} (saved by other code)")
        carry = jax.tree.unflatten(treedef, [
            jax.random.wrap_key_data(z[f"carry{i}"]) if i in meta["keys"] else
            jnp.asarray(z[f"carry{i}"], like.dtype) for i, like in enumerate(leaves)])
        traces = [Trace(**{f: z[f"trace{k}_{f}"] for f in Trace._fields})
                  for k in range(meta["chunks"])]
    return carry, traces, meta["steps"], meta["run_s"]


def _same_run(saved: str, now: str) -> bool:
    """Whether a saved state's run identity and this run's (the JSON of :func:`run`'s ``ident``)
    differ only by settings added to the code since the state was saved, here at their defaults
    (they ran so before they existed): a new setting does not strand the states already saved
    (session 89's ``trust_component`` beside the G1 oracle's cut episode)."""
    defaults = json.loads(json.dumps(
        {k: v for k, v in dataclasses.asdict(ClosedLoopConfig()).items() if k not in _PER_RUN},
        default=str))

    def new_at_default(old, new, default):  # ``new`` less the keys ``old`` lacks at default
        if not (isinstance(old, dict) and isinstance(new, dict)):
            return new
        default = default if isinstance(default, dict) else {}
        return {k: new_at_default(old[k], v, default.get(k)) if k in old else v
                for k, v in new.items() if k in old or k not in default or default[k] != v}
    try:
        a, b = json.loads(saved), json.loads(now)
    except ValueError:
        return False
    if not (isinstance(a, dict) and isinstance(b, dict) and "settings" in b):
        return False
    b["settings"] = new_at_default(a.get("settings"), b["settings"], defaults)
    return a == b


def _ident_difference(saved: str, now: str, most: int = 4) -> str:
    """What differs between a saved state's run identity and this run's (both the JSON of
    :func:`run`'s ``ident``), as ``key: saved -> now`` for the first ``most`` keys."""
    def flat(d, pre=""):
        out = {}
        for k, v in d.items():
            if isinstance(v, dict):
                out.update(flat(v, f"{pre}{k}."))
            else:
                out[f"{pre}{k}"] = v
        return out
    try:
        a, b = flat(json.loads(saved)), flat(json.loads(now))
    except (ValueError, AttributeError):
        return "it was saved by another run"
    gone = "(absent)"
    diff = [f"{k}: {a.get(k, gone)} -> {b.get(k, gone)}" for k in sorted(a.keys() | b.keys())
            if a.get(k, gone) != b.get(k, gone)]
    more = f"; and {len(diff) - most} more" if len(diff) > most else ""
    return "another run's settings (" + "; ".join(diff[:most]) + more + ")"


def _set_aside(path: pathlib.Path) -> pathlib.Path:
    """``path`` renamed ``<stem>.stale<k>.npz`` (the first ``k`` free), so that a run which does
    not resume it never overwrites it."""
    k = 0
    while (aside := path.with_name(f"{path.stem}.stale{k}{path.suffix}")).exists():
        k += 1
    path.rename(aside)
    return aside


def _chunked(fns, args, n_steps: int, chunk: int, batched: bool, partial: pathlib.Path,
             ident: str, now: dict, log: Callable):
    """One pair's episodes chunk by chunk, saved after each and resumed from ``partial``:
    ``(traces, run_s)``, ``run_s`` the chunks' wall time (resumed ones' included)."""
    start, resume = fns
    carry = start(*args)
    got = _load_state(partial, carry, ident)
    traces, steps, run_s = [], 0, 0.0
    if isinstance(got, str):  # not this run's: kept aside, never overwritten
        log(f"  {now['label']}: {partial} is not resumed: {got}; kept as "
            f"{_set_aside(partial).name}, the episode starts from its first step")
    elif got is not None:
        carry, traces, steps, run_s = got
        log(f"  {now['label']}: resumed at {min(steps, n_steps)} of {n_steps} steps ({partial})")
    axis = 1 if batched else 0
    while steps < n_steps:
        t0 = time.perf_counter()
        carry, trace = jax.block_until_ready(resume(carry, steps, *args))
        run_s += time.perf_counter() - t0
        traces.append(jax.tree.map(np.asarray, trace))
        steps += chunk
        _save_state(partial, carry, traces, steps, run_s, ident)
    joined = jax.tree.map(lambda *xs: np.concatenate(xs, axis)[(slice(None),) * axis
                                                                + (slice(0, n_steps),)], *traces)
    return joined, run_s  # the saved state stays until the pair's rows are written


def _drop_state(partial: pathlib.Path) -> None:
    """A pair's saved state, once its rows are written (never before: a run killed between
    its last chunk and its rows, timing the controller say, resumes at its end rather than
    losing the episode, as session 88's oracle did), and the folder once no pair has one."""
    partial.unlink(missing_ok=True)
    with contextlib.suppress(OSError):
        partial.parent.rmdir()


def trace_name(scenario: str, model: str, episode: int = 0, seed: int = 0) -> str:
    """A row's trace file: ``trace_<scenario>_<model>.npz`` for a pair's first episode (the
    one the figures draw), ``..._seed<seed>.npz`` for the others."""
    return f"trace_{scenario}_{model}" + (f"_seed{seed}" if episode else "") + ".npz"


def over_seeds(rows: list[dict]) -> list[dict]:
    """Per (scenario, model) with more than one episode: how many episodes, how many fell, and
    the median, min and max velocity RMSE of the episodes that stayed up (NaN: none did)."""
    groups: dict[tuple[str, str], list[dict]] = {}
    for r in rows:
        groups.setdefault((r["scenario"], r["model"]), []).append(r)
    out = []
    for (sc, model), got in groups.items():
        if len(got) < 2:
            continue
        up = [r["vel_rmse"] for r in got if not r["fell"]]
        out.append(dict(scenario=sc, model=model, episodes=len(got),
                        falls=sum(bool(r["fell"]) for r in got),
                        seeds=[r.get("seed") for r in got],
                        vel_rmse_median=float(np.median(up)) if up else float("nan"),
                        vel_rmse_min=float(min(up)) if up else float("nan"),
                        vel_rmse_max=float(max(up)) if up else float("nan")))
    return out


def scenario(cfg: ClosedLoopConfig, name: str) -> Scenario:
    """The scenario ``name`` with the run's overrides: ``cfg.seconds``, ``cfg.slope_deg`` for a
    scenario with a slope, ``cfg.rough_cm`` for one with rough ground, ``cfg.push_scale`` for one
    with pushes, ``cfg.friction`` for one with a lowered friction and ``cfg.payload`` for one
    with a payload (renamed with the angle, height, factor or value, ``tilt15``, ``rough2``,
    ``push3x``, ``low_friction0.15``, ``payload0.4``; ``cfg.payload_body`` adds ``_on_torso_link``), so that
    rows of different scenarios never share a name); with ``cfg.sensor_noise`` the name gets
    its factor (``rough2_noise3``: the controller sees through noisier sensors)."""
    sc = SCENARIOS[name]
    if cfg.seconds:
        sc = dataclasses.replace(sc, seconds=cfg.seconds)
    if cfg.slope_deg and sc.slope_deg:
        sc = dataclasses.replace(sc, name=f"{sc.name}{cfg.slope_deg:g}", slope_deg=cfg.slope_deg)
    if cfg.rough_cm and sc.rough_m:
        sc = dataclasses.replace(sc, name=f"{sc.name}{cfg.rough_cm:g}", rough_m=cfg.rough_cm / 100)
    if cfg.push_scale and sc.pushes:
        pushes = tuple((t, d, cfg.push_scale * dvx, cfg.push_scale * dvy) for t, d, dvx, dvy in sc.pushes)
        sc = dataclasses.replace(sc, name=f"{sc.name}{cfg.push_scale:g}x", pushes=pushes)
    if cfg.friction and sc.friction != 1.0:
        sc = dataclasses.replace(sc, name=f"{sc.name}{cfg.friction:g}", friction=cfg.friction)
    if cfg.payload and sc.payload:
        sc = dataclasses.replace(sc, name=f"{sc.name}{cfg.payload:g}", payload=cfg.payload)
    if cfg.payload_body and sc.payload:
        sc = dataclasses.replace(sc, name=f"{sc.name}_on_{cfg.payload_body}", payload_body=cfg.payload_body)
    if cfg.sensor_noise:
        sc = dataclasses.replace(sc, name=f"{sc.name}_noise{cfg.sensor_noise:g}")
    return sc


def _fmt(x, f: str = "{:.3f}") -> str:
    """A table cell: ``-`` for a missing or NaN value."""
    return "-" if x is None or (isinstance(x, float) and np.isnan(x)) else f.format(x)


_GATE_READS = {"norm": "linear estimate", "down": "downward estimate"}


def _gate_words(pl) -> str:
    """What trips the model-trust gate, in words (the run's summary line)."""
    return " or ".join(
        ([f"the observer's {_GATE_READS[pl.trust_component]} exceeds {pl.trust_limit:g} m/s^2"]
         if pl.trust_limit else [])
        + ([f"the forward velocity exceeds the command by {pl.trust_overshoot:g} m/s"]
           if pl.trust_overshoot else []))


def write(rows: list[dict], cfg: ClosedLoopConfig, command: str, out: pathlib.Path,
          code: str | None = None) -> None:
    """``closed_loop.json`` and ``.md`` (and the plots) of ``rows``; ``code``: the commit the run
    started from (default: the checkout's now)."""
    env = dict(command=command, backend=jax.default_backend(), device=jax.devices()[0].device_kind,
               jax=jax.__version__, code=code or code_version(), config=dataclasses.asdict(cfg))
    atomic_write_text(out / "closed_loop.json", json.dumps(dict(env=env, rows=rows), indent=1))
    robot = {"go1": "Go1", "g1": "G1"}.get(cfg.robot, cfg.robot)
    pl = cfg.planning
    gated = pl.trust_gated
    extras = "".join([
        f", tracking weight {pl.learned_track_weight:g} on the learned reward"
        if cfg.learned and pl.learned_track_weight else "",
        f", disturbance observer (gain {pl.observer_gain:g})" if pl.observer_gain else "",
        (f", the policy acts while {_gate_words(pl)}"
         + (f" for {pl.trust_delay_s:g} s in a row" if pl.trust_delay_s else "")
         + f" (held {pl.trust_hold_s:g} s; the model-trust gate: share of upright steps in the"
         " last column)") if gated else "",
        f", {cfg.mppi.family_samples} candidates from the policy asked for command + z"
        if cfg.mppi.family_samples else ""])
    lines = [f"# Closed-loop MPPI on the MJX {robot}", "", f"Command: `{command}`", "",
             f"Device: {env['device']} ({env['backend']}), jax {env['jax']}. MPPI K={cfg.mppi.samples}, "
             f"H={cfg.mppi.horizon}, {cfg.mppi.iterations} iteration(s); cost: "
             f"{'learned reward/value ' + cfg.learned if cfg.learned else 'analytic reward terms'}"
             f"{', gait parameters planned' if cfg.planning.gait else ''}"
             f"{', PPO candidates from ' + cfg.policy if cfg.policy and cfg.mppi.policy_samples else ''}"
             f"{extras}. Tracking RMSE of the base-frame velocity (xy) and yaw rate while upright, "
             f"{cfg.settle_s} s after each command change.", "",
             "Gait: the named pattern the measured foot contacts fit best (score: in-phase minus "
             "anti-phase contact correlation); with planned gaits, the median planned "
             "parameters too.", "",
             "| scenario | model | vel RMSE (m/s) | yaw RMSE (rad/s) | mean vx (m/s) | fell | "
             "fall at (s) | contact gait (score) | planned gait | ms/step | controller ms |"
             + (" policy acted |" if gated else ""),
             "|---|---|---|---|---|---|---|---|---|---|---|" + ("---|" if gated else "")]
    for r in rows:
        planned = (f"{r['plan_gait']} ({r['plan_freq']:.1f} Hz, duty {r['plan_duty']:.2f})"
                   if "plan_gait" in r else "-")
        contact = (f"{r['contact_gait']} ({r['contact_gait_score']:.2f})"
                   if "contact_gait" in r else "-")
        model = r["model"] + (f" (seed {r['seed']})" if cfg.episodes > 1 else "")
        lines.append(f"| {r['scenario']} | {model} | {_fmt(r['vel_rmse'])} | "
                     f"{_fmt(r['yaw_rmse'])} | {_fmt(r['mean_vx'], '{:.2f}')} | "
                     f"{'yes' if r['fell'] else 'no'} | {_fmt(r['fall_s'], '{:.2f}')} | "
                     f"{contact} | {planned} | {r['ms_per_step']:.1f} | "
                     f"{_fmt(r.get('controller_ms'), '{:.1f}')} |"
                     + (f" {_fmt(r.get('distrust_share'), '{:.0%}')} |" if gated else ""))
    lines += _over_seeds_lines(rows)
    atomic_write_text(out / "closed_loop.md", "\n".join(lines) + "\n")


def _over_seeds_lines(rows: list[dict]) -> list[str]:
    """The markdown table of :func:`over_seeds` (nothing when every pair ran one episode)."""
    summary = over_seeds(rows)
    if not summary:
        return []
    lines = ["", "Over seeds (the planner's draws; ms/step above is the wall time of one "
             "control step of a pair's episodes side by side):", "",
             "| scenario | model | episodes | fell | vel RMSE median of those up (min - max) |",
             "|---|---|---|---|---|"]
    for g in summary:
        lines.append(f"| {g['scenario']} | {g['model']} | {g['episodes']} | {g['falls']} | "
                     f"{_fmt(g['vel_rmse_median'])} ({_fmt(g['vel_rmse_min'])} - "
                     f"{_fmt(g['vel_rmse_max'])}) |")
    return lines


def _run_seed(env: dict | None) -> int:
    """A part's ``--seed`` (its ``env``'s config), the seed of rows written before rows had one."""
    return ((env or {}).get("config") or {}).get("seed", 0)


# a run's settings that say which draws it took, where it wrote, how it batched its episodes or
# how long it timed the controller alone, not which planner it was nor what its episodes did
_PER_RUN = frozenset({"seed", "episodes", "out", "models", "scenarios", "progress_s", "chunk_s",
                      "controller_repeats", "together"})


# Settings added with a default other than the behaviour of the runs before them: a run's
# config without the key ran as the value here.
_BEFORE = {"sense_gravity": False}


def _settings(env: dict | None, model: str) -> dict:
    """What makes a part's row of ``model`` one planner: its run's config (``env['config']``)
    less the keys that only pick draws, scenarios or the output (``_PER_RUN``), plus the file
    the model was loaded from where the run names one (``--models NAME=PATH``; not ``policy``,
    ``oracle``, ...; nor a run that kept no config: what it lacks is not compared)."""
    config = dict((env or {}).get("config") or {})
    paths = dict(m.split("=", 1) for m in str(config.get("models", "")).split(",") if "=" in m)
    kept = {k: v for k, v in config.items() if k not in _PER_RUN}
    if config:  # settings whose absence means the behaviour before them, not today's default
        kept = {**_BEFORE, **kept}
    path = paths.get(model.split("@")[0])
    return {**kept, "model_file": path} if path else kept


def _same_settings(a: dict, b: dict) -> bool:
    """Two runs' :func:`_settings` agree on every key both carry (nested: ``mppi``,
    ``planning``); a key one lacks is a setting added since the older run, at its default."""
    for k in a.keys() & b.keys():
        x, y = a[k], b[k]
        if isinstance(x, dict) and isinstance(y, dict):
            if not _same_settings(x, y):
                return False
        elif x != y:
            return False
    return True


def merge(parts: list[str], out: str, title: str = "", onto: str | None = None,
          headline: list[str] | None = None) -> list[dict]:
    """One table from several runs' folders (``closed_loop.json`` each: runs split over device
    calls, or variants of the planner): every row keeps its part's name (``part``) and the part's
    command and device go to ``closed_loop.json``'s ``parts``. A part may also be a JSON file of
    rows recovered from a run's log (``{"env": {...}, "rows": [...]}``, rows with at least
    ``scenario``, ``model``, ``vel_rmse``, ``fell``, ``ms_per_step``). Traces found beside a
    part are copied, so the plots show every row. A (scenario, model) pair of which an earlier
    part already has an episode (same seed), or which an earlier part ran with other settings
    (:func:`_settings`: another model file or planner flag), is renamed ``model@part``, all its
    episodes; parts that differ only in their seeds are draws of one planner and keep one name.
    ``onto``: a merged ``closed_loop.json`` whose rows (with any notes added to them since) and
    parts are kept as they are, the new parts' rows appended after them (its title unless
    ``title`` is given); a part merged there before adds the rows its run has written since (a
    resumed run), and none new is an error. ``headline``: the parts that hold the current
    planner's rows (the report's closed-loop claims read those alone; kept from ``onto`` when not
    given), each ``PART`` (all its rows) or ``PART:MODEL+MODEL`` (only those models' rows, by
    their name in the part's run: a run's policy-alone rows without its planner's); each part
    must be a part of the table; ``PART/SCENARIO+SCENARIO`` takes only those scenarios' rows (a
    part whose other scenarios a later planner setting has replaced; the grammar, its check and
    its reading: :mod:`stride_jax.jobs.headline`)."""
    import shutil

    out_dir = pathlib.Path(out)
    out_dir.mkdir(parents=True, exist_ok=True)
    rows, envs_, seen, head = [], {}, set(), None
    if onto is not None:
        base = json.loads(pathlib.Path(onto).read_text())
        rows, envs_ = list(base["rows"]), dict(base["parts"])
        title = title or base.get("title", "")
        head = base.get("headline")
        seen = {(r["scenario"], r["model"], r.get("seed", _run_seed(envs_.get(r.get("part")))))
                for r in rows}
    # the settings each (scenario, model) name has run with so far (each distinct one once)
    settings: dict[tuple[str, str], list[dict]] = {}

    def ran(pair: tuple[str, str], setting: dict) -> None:
        if setting not in settings.setdefault(pair, []):
            settings[pair].append(setting)

    for r in rows:
        ran((r["scenario"], r["model"]), _settings(envs_.get(r.get("part")), r["model"]))
    for part in parts:
        path = pathlib.Path(part)
        src = path / "closed_loop.json" if path.is_dir() else path
        if not src.is_file():
            raise FileNotFoundError(f"{src}: no closed_loop.json to merge")
        data = json.loads(src.read_text())
        name = path.name if path.is_dir() else path.stem
        # rows written before ``seed`` was: the part's --seed, as the run's resume reads them
        run_seed = _run_seed(data["env"])
        for r in data["rows"]:
            missing = {"scenario", "model", "vel_rmse", "fell", "ms_per_step"} - set(r)
            if missing:
                raise ValueError(f"{src}: a row lacks {sorted(missing)}")
        part_rows, clash = data["rows"], set()
        if name in envs_:  # merged before: only the rows its run has added since (a resume)
            have = {(r["scenario"], r["model"].split("@")[0], r.get("seed", run_seed)): r
                    for r in rows if r.get("part") == name}
            part_rows = [r for r in part_rows
                         if (r["scenario"], r["model"], r.get("seed", run_seed)) not in have]
            if not part_rows:
                raise ValueError(f"{part}: a part named {name!r} is already merged (no new rows)")
            clash = {k[:2] for k, r in have.items() if r["model"] != k[1]}  # renamed then
        envs_[name] = data["env"]
        mine = {m: _settings(data["env"], m) for m in {r["model"] for r in part_rows}}
        # a second part's variant of the same model: all of its episodes of that pair renamed
        # (an episode clashing renames its pair, so one part's draws keep one name)
        clash |= {(r["scenario"], r["model"]) for r in part_rows
                  if (r["scenario"], r["model"], r.get("seed", run_seed)) in seen
                  or not all(_same_settings(mine[r["model"]], other)
                             for other in settings.get((r["scenario"], r["model"]), []))}
        for r in part_rows:
            model, episode, seed = r["model"], r.get("episode", 0), r.get("seed", run_seed)
            if (r["scenario"], model) in clash:
                model = f"{model}@{name}"
            seen.add((r["scenario"], model, seed))
            ran((r["scenario"], model), mine[r["model"]])
            rows.append({**r, "model": model, "part": name})
            trace = src.parent / trace_name(r["scenario"], r["model"], episode, seed)
            if trace.is_file():
                shutil.copy2(trace, out_dir / trace_name(r["scenario"], model, episode, seed))
    if headline is not None:
        check_entries(headline, envs_, rows)
        head = dict(parts=list(headline))
    table = dict(title=title, parts=envs_, rows=rows)
    if head is not None:
        table["headline"] = head
    atomic_write_text(out_dir / "closed_loop.json", json.dumps(table, indent=1))
    lines = [f"# {title or 'Closed-loop MPPI'}", "", "Parts (each row names its part):", ""]
    lines += [f"- `{k}`: `{v.get('command', '')}` ({v.get('device', '?')})"
              for k, v in envs_.items()]
    if head is not None:
        lines += ["", f"The current planner (the report's claims read these parts' rows alone): "
                      f"{', '.join(f'`{h}`' for h in head['parts'])}."]
    timed = any(r.get("controller_ms") is not None for r in rows)  # (parts since session 80)
    lines += ["", "| scenario | model | part | vel RMSE (m/s) | yaw RMSE (rad/s) | mean vx (m/s) | "
              "fell | fall at (s) | ms/step |" + (" controller ms |" if timed else ""),
              "|---|---|---|---|---|---|---|---|---|" + ("---|" if timed else "")]
    for r in rows:
        lines.append(f"| {r['scenario']} | {r['model']} | {r['part']} | {_fmt(r['vel_rmse'])} | "
                     f"{_fmt(r.get('yaw_rmse'))} | {_fmt(r.get('mean_vx'), '{:.2f}')} | "
                     f"{'yes' if r['fell'] else 'no'} | {_fmt(r.get('fall_s'), '{:.2f}')} | "
                     f"{r['ms_per_step']:.1f} |"
                     + (f" {_fmt(r.get('controller_ms'), '{:.1f}')} |" if timed else ""))
    lines += _over_seeds_lines(rows)
    atomic_write_text(out_dir / "closed_loop.md", "\n".join(lines) + "\n")
    plot(out_dir, rows)
    return rows


def plot(out: pathlib.Path, rows: list[dict]) -> list[pathlib.Path]:
    """One figure per scenario: forward velocity and yaw rate against the command, per model
    whose trace (``trace_<scenario>_<model>.npz``: a pair's first episode) lies in ``out``. A
    scenario without any trace leaves its figure as it is (a merge of parts whose traces were
    not kept must not blank it)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    for sc in dict.fromkeys(r["scenario"] for r in rows):
        traced = [r for r in rows if r["scenario"] == sc and not r.get("episode", 0)
                  and (out / trace_name(sc, r["model"])).is_file()]
        if not traced:
            continue
        fig, ax = plt.subplots(1, 3, figsize=(14, 3.6))
        cmd_drawn = False
        for r in traced:
            tr = np.load(out / trace_name(sc, r["model"]))
            if not cmd_drawn:
                for i, label in enumerate(("vx", "vy", "yaw rate")):
                    ax[i].plot(tr["t"], tr["command"][:, i], "k--", lw=1, label="command")
                cmd_drawn = True
            up = ~tr["fallen"]
            for i, series in enumerate((tr["v_base"][:, 0], tr["v_base"][:, 1],
                                        tr["w_base"][:, 2])):
                ax[i].plot(tr["t"][up], series[up], lw=1, label=r["model"])
        for i, label in enumerate(("vx (m/s)", "vy (m/s)", "yaw rate (rad/s)")):
            ax[i].set(xlabel="t (s)", ylabel=label)
        ax[0].legend(fontsize=7)
        fig.suptitle(f"closed loop, scenario {sc} (lines stop at a fall)")
        fig.tight_layout()
        path = out / f"closed_loop_{sc}.png"
        fig.savefig(path, dpi=90)
        plt.close(fig)
        paths.append(path)
    return paths


def parse_pick(spec: str, flag: str = "--planner") -> tuple[str, str, tuple[str, ...]]:
    """``LABEL=MODEL[@PART,PART...]`` -> ``(label, model, parts)``: a labelled choice of rows for
    :func:`select` (the figures' command lines); a malformed spec is an error naming ``flag``."""
    label, sep, pick = spec.partition("=")
    if not sep or not label or not pick:
        raise ValueError(f"{flag} {spec!r}: expected LABEL=MODEL[@PART,PART...]")
    model, _, parts = pick.partition("@")
    return label, model, tuple(p for p in parts.split(",") if p)


def select(rows: list[dict], model: str, parts: tuple[str, ...] = ()) -> dict[str, dict]:
    """``{scenario: row}`` of ``model`` (a merged row's name before any ``@part``), from the
    first of ``parts`` that has the scenario (``parts`` empty: any part, the first row wins)."""
    order = {p: i for i, p in enumerate(parts)}
    best: dict[str, tuple[int, dict]] = {}
    for r in rows:
        part = r.get("part", "")
        if r["model"].split("@")[0] != model or (parts and part not in order):
            continue
        rank = order.get(part, 0)
        if r["scenario"] not in best or rank < best[r["scenario"]][0]:
            best[r["scenario"]] = (rank, r)
    return {sc: r for sc, (_, r) in best.items()}


def bars(planners: dict[str, dict[str, dict]], scenarios: list[str], out: str | pathlib.Path,
         title: str = "", labels: dict[str, str] | None = None,
         ylim: float | None = None) -> pathlib.Path:
    """Velocity RMSE per scenario as grouped bars, one colour per planner (``{label: {scenario:
    row}}``); a fall is a hatched bar marked with its time, a missing row leaves a gap. Writes
    the PNG ``out`` atomically."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from stride_jax import io

    fig, ax = plt.subplots(figsize=(max(8.0, 1.3 * len(scenarios) + 2), 4.2))
    width = 0.8 / max(len(planners), 1)
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    top = ylim or 1.1 * max((r["vel_rmse"] for got in planners.values() for r in got.values()),
                            default=1.0)
    for i, (label, got) in enumerate(planners.items()):
        for j, sc in enumerate(scenarios):
            r = got.get(sc)
            if r is None:
                continue
            x = j - 0.4 + (i + 0.5) * width
            h = min(r["vel_rmse"], top)  # a fall's RMSE can dwarf the rest: clipped, marked
            ax.bar(x, h, width, color=colors[i % len(colors)], label=label,
                   hatch="//" if r["fell"] else None, edgecolor="k" if r["fell"] else None)
            label = None  # one legend entry per planner
            note = f"{r['vel_rmse']:.2f}" if r["vel_rmse"] > top else ""
            if r["fell"]:
                note += " fell" + (f" {r['fall_s']:.1f} s" if r.get("fall_s") is not None else "")
            if r["vel_rmse"] > top:  # clipped: the value inside the bar
                ax.text(x, 0.98 * top, note.strip(), ha="center", va="top", fontsize=6,
                        rotation=90)
            elif note:
                ax.text(x, h + 0.01 * top, note.strip().replace(" ", "\n", 1), ha="center",
                        va="bottom", fontsize=6)
    ax.set_xticks(range(len(scenarios)))
    ax.set_xticklabels([(labels or {}).get(s, s) for s in scenarios])
    ax.set_ylabel("velocity RMSE while upright (m/s)")
    ax.set_ylim(0, top if ylim else top * 1.1)
    ax.set_title(title, fontsize=10)
    ax.legend(fontsize=7, loc="best")
    fig.tight_layout()
    path = pathlib.Path(out)
    io.atomic_write(path, lambda f: fig.savefig(f, format="png", dpi=130))
    plt.close(fig)
    return path


def main(argv: list[str] | None = None) -> None:
    config.config_main("python -m stride_jax.jobs.closed_loop", ClosedLoopConfig, PRESETS, run,
                      argv, __doc__.split("\n")[0])


if __name__ == "__main__":
    stride_jax.set_xla_flags()  # before JAX starts: small CPUs deadlock without
    main()
