"""``stride train`` / ``make train``: dataset -> model -> trained, checkpointed params.

The job's config nests the library's: the networks' (:class:`~stride_jax.dynamics.mlp.MLPConfig`,
``net``) and the loop's (:class:`~stride_jax.train.loop.LoopConfig`, ``loop``); the model's
config and normalisers come from :mod:`stride_jax.train.setup`, the training from
:mod:`stride_jax.train.dynamics` (around :mod:`stride_jax.train.loop`). Presets are named instances (:data:`PRESETS`).
"""

from __future__ import annotations

import dataclasses
import json
import pathlib
from typing import ClassVar

from stride_jax import distributed, robots
from stride_jax.distributed import DistributedConfig
from stride_jax.dynamics import checkpoint, models
from stride_jax.dynamics.mlp import MLPConfig
from stride_jax.dynamics.models import spec_from_meta
from stride_jax.eval import forces
from stride_jax.io import atomic_write_text, code_version
from stride_jax.jobs import data as data_job
from stride_jax.sim import dataset
from stride_jax.sim import model as sim_model
from stride_jax.train import dynamics as train_dynamics
from stride_jax.train.loop import LoopConfig
from stride_jax.train.setup import model_config, scales


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """What ``stride train`` trains.

    Attributes:
      robot: pendulum, pendulum_bouncing, go1 or g1.
      model: stride, delan, lnn_diffusion, onn or diffusion (see ``models.MODELS``).
      data: dataset folder; empty means ``data/<robot>`` (``stride data`` makes it).
      make_data: generate a missing dataset first (``stride data`` with ``data_preset``);
        without it a missing dataset is an error that says how to make it.
      data_preset: the ``stride data`` preset ``make_data`` uses.
      net: every network of the model (:class:`~stride_jax.dynamics.mlp.MLPConfig`:
        ``--net.hidden``, ``--net.depth``, ``--net.activation``, ``--net.init``; the older flags
        ``--hidden``, ``--depth``, ``--activation``, ``--weight-init`` still answer). Defaults:
        ``MLPConfig``'s, 256 x 3, the paper's; the ``default`` preset is CPU-sized, 128 x 3.
      loop: the optimisation (:class:`~stride_jax.train.loop.LoopConfig`: ``--loop.steps``,
        ``--loop.batch``, ``--loop.lr``, ``--loop.eval-every``, ``--loop.ckpt-every``,
        ``--loop.seed``, ``--loop.deadline``; the older ``--steps``, ``--batch``, ``--lr``,
        ``--eval-every``, ``--ckpt-every``, ``--seed``, ``--deadline`` still answer).
      nfe: network evaluations per sample of a generative model; 0 means the model's default
        (``models.DEFAULT_NFE``: 2 for the flow, 10 for diffusion).
      shared_lnn: structured models: L and V from one network (``LNNConfig.shared``).
      acc_through: generative structured models: what the acceleration loss trains besides the
        prior (``stride.ACC_THROUGH``: prior, central, sample, mean).
      learn_mass: structured models on a floating base: learn the total mass (starting at the
        spec sheet's) instead of holding it there (an ablation of the fixed mass).
      base_structure: structured models on a floating base: M's translational block ``m I``,
        ``V = m g z + V_net`` and no base position among the prior's inputs
        (``LNNConfig.base_structure``); ``--no-base-structure`` learns a generic Lagrangian of
        the base's coordinates instead (an ablation of the structure).
      potential: structured models on a floating base with the structure: ``net`` (``V = m g z
        + V_net(orientation, joints)``, as trained until session 47) or ``com``, gravity's exact
        multibody form with a centre-of-mass offset learned from the joints
        (``LNNConfig.potential``: exact under any gravity direction, ``--planning.model-gravity``).
      gravity_context: every model's networks also see gravity's direction in the base's frame
        (``StructuredConfig.gravity_context``): for data whose gravity varies (``stride data
        --slope-deg``), where the residual's contact forces (and a next-observation model's
        whole step) depend on the slope; the structured models' prior is told it either way.
      transition_weight: structured models: weight of the one-control-period transition loss
        (``StructuredConfig.transition_weight``: the model's own step through the period's
        substeps against the logged next state, in the one-step changes' units); 0, the
        default, trains on accelerations alone, as the paper.
      transition_fraction: the share of each minibatch the transition term is computed on
        (``StructuredConfig.transition_fraction``; 1: every example). The term costs ~5x an
        acceleration step per example; validation takes every example.
      base_weight: floating bases: the weight of the base's six dofs in the one-control-period
        losses (``StructuredConfig.base_weight``: the structured models' transition term, which
        it needs, and ONN's whole loss), 1 for each joint; 1, the default, weighs every dof
        alike. Above 1 trains for the base's motion, what a velocity-tracking planner's cost
        reads.
      out: run folder; empty means ``runs/<robot>/<model>``.
      seeds: several seeds trained side by side in one program (comma-separated, e.g.
        ``0,1,2``; :func:`stride_jax.train.dynamics.train_side_by_side`), each into its own run
        folder ``<out>-s<seed>``, each the run ``--loop.seed`` alone makes (its initialisation
        and draws; the batched products round differently); empty: one run of ``loop.seed``
        into ``out`` (``--seed`` and ``--seeds`` together: an error). On a GPU at the paper's
        size three seeds take 1.4x one seed's step (``results/throughput/README.md``); on a CPU
        they gain nothing. Several local devices share the seeds where they split evenly (else
        all train on the first).
      distributed: train data-parallel over several processes (:mod:`stride_jax.distributed`).
    """

    robot: str = "pendulum"
    model: str = "stride"
    data: str = ""
    make_data: bool = False
    data_preset: str = "default"
    net: MLPConfig = MLPConfig()
    loop: LoopConfig = LoopConfig()
    nfe: int = 0
    shared_lnn: bool = False
    acc_through: str = "central"
    learn_mass: bool = False
    base_structure: bool = True
    potential: str = "net"
    gravity_context: bool = False
    transition_weight: float = 0.0
    transition_fraction: float = 1.0
    base_weight: float = 1.0
    out: str = ""
    seeds: str = ""
    distributed: DistributedConfig = DistributedConfig()

    # The flat flags of earlier commands (README, Makefile, recorded runs) still answer.
    FLAG_ALIASES: ClassVar[dict[str, str]] = {
        **{f"net.{name}": f"--{name}" for name in ("hidden", "depth", "activation")},
        "net.init": "--weight-init",
        **{f"loop.{f.name}": "--" + f.name.replace("_", "-")
           for f in dataclasses.fields(LoopConfig)}}


PRESETS = {
    "tiny": TrainConfig(net=MLPConfig(hidden=32, depth=2),
                        loop=LoopConfig(steps=100, batch=64, eval_every=50, ckpt_every=50),
                        data_preset="tiny"),
    # CPU-sized (``results/table1/go1_cpu``): 128 x 3 networks, the loop's 2000 steps of 256.
    "default": TrainConfig(net=MLPConfig(hidden=128)),
    # The committed Table I (``results/table1/go1``, ``results/table1/g1``; H100): MLPConfig's
    # 256 x 3, batch 1024, 12k steps (the Go1 tables; the G1 tables ran ``--steps 8000``), each
    # run also under a wall-clock budget (``experiments/table1.py --minutes``). The one source of
    # these numbers: ``experiments/table1.py`` and ``experiments/reproduce.py`` use this preset
    # as it is.
    "paper": TrainConfig(loop=LoopConfig(steps=12_000, batch=1024, lr=1e-3, eval_every=1000,
                                         ckpt_every=2000),
                         data_preset="paper"),
}


def run(cfg: TrainConfig, command: str = "stride train", log=print) -> pathlib.Path:
    """Trains ``cfg.model`` on ``cfg.data`` into ``cfg.out`` (with ``cfg.seeds``: into
    ``<out>-s<seed>`` each; resuming a killed run); returns the run folder (the first seed's).
    ``command`` is accepted for the uniform job signature."""
    models.check_name(cfg.model)  # before any data is made for it
    seeds = parse_seeds(cfg.seeds)
    if seeds and cfg.loop.seed != LoopConfig.seed:
        raise ValueError(f"--seed {cfg.loop.seed} with --seeds {cfg.seeds}: give every seed in --seeds alone")
    if seeds and distributed.resolve(cfg.distributed) is not None:
        raise ValueError("--seeds trains side by side on one process; with --distributed train the seeds one by one")
    distributed.initialize(cfg.distributed)
    data_dir = pathlib.Path(cfg.data or f"data/{cfg.robot}")
    if not (data_dir / "meta.json").exists():
        robots.get(cfg.robot)  # an unknown robot is named as such, not as a missing dataset
        if not cfg.make_data:
            raise dataset.DatasetError(
                f"no dataset at {data_dir}: make it first with `stride data --robot {cfg.robot} "
                f"--preset {cfg.data_preset} --out {data_dir}`, or train with --make-data")
        log(f"no dataset at {data_dir}: generating one (preset {cfg.data_preset})")
        data_job.generate(dataclasses.replace(data_job.PRESETS[cfg.data_preset], robot=cfg.robot,
                                              out=str(data_dir), distributed=cfg.distributed))
    ds = dataset.load(data_dir, robot=cfg.robot)
    if "act_dof" not in ds.meta:
        raise dataset.DatasetError(f"{data_dir} predates actuator metadata; regenerate it")
    spec = spec_from_meta(ds.meta)
    model_cfg = model_config(cfg.model, ds.meta, cfg.net.hidden, cfg.net.depth, cfg.nfe,
                             cfg.shared_lnn, cfg.acc_through, cfg.learn_mass, cfg.net.activation,
                             cfg.net.init, cfg.base_structure, cfg.transition_weight,
                             cfg.transition_fraction, cfg.potential, cfg.gravity_context,
                             cfg.base_weight)
    act = models.Actuation.from_meta(ds.meta)
    sc = scales(ds)
    model = models.make(cfg.model, spec, act, model_cfg, sc)
    out = pathlib.Path(cfg.out or f"runs/{cfg.robot}/{cfg.model}")
    runs = {s: out.parent / f"{out.name}-s{s}" for s in seeds} or {cfg.loop.seed: out}
    if distributed.is_main():
        for seed, run_dir in runs.items():
            run_dir.mkdir(parents=True, exist_ok=True)
            checkpoint.save_definition(run_dir, model)
            # each folder's config is the single run it equals (its seed, its folder)
            own = dataclasses.replace(cfg, loop=dataclasses.replace(cfg.loop, seed=seed), out=str(run_dir), seeds="")
            atomic_write_text(run_dir / "config.json", json.dumps(
                {"train": dataclasses.asdict(own), "dataset": str(data_dir), "code": code_version(),
                 "dataset_sha256": ds.meta["arrays_sha256"], **({"side_by_side": seeds} if seeds else {})},
                indent=1))
    jacobians = None
    if ds.meta["feet"]:
        sm = sim_model.load(ds.meta["robot"])
        jacobians = lambda q: forces.foot_jacobians(sm, q)  # noqa: E731
    data = train_dynamics.examples(ds.split("train"), jacobians)
    val = train_dynamics.examples(ds.split("val"), jacobians)
    if seeds:
        train_dynamics.train_side_by_side(model.loss, model.init, data, val, cfg.loop, runs, log,
                                          batch_loss=model.batch_loss)
    else:
        train_dynamics.train_examples(model.loss, model.init, data, val, cfg.loop, out, log,
                                      batch_loss=model.batch_loss)
    for run_dir in runs.values():
        log(f"trained {cfg.model} on {cfg.robot}: best params in {run_dir / 'best'}, "
            f"log in {run_dir / 'metrics.csv'}")
    return out if not seeds else runs[seeds[0]]


def parse_seeds(text: str) -> list[int]:
    """``--seeds`` (``"0,1,2"``) as distinct non-negative integers; empty: none."""
    if not text.strip():
        return []
    try:
        seeds = [int(s) for s in text.split(",")]
    except ValueError:
        raise ValueError(f"--seeds {text!r}: need comma-separated integers, e.g. 0,1,2") from None
    if len(set(seeds)) != len(seeds) or min(seeds) < 0:
        raise ValueError(f"--seeds {text!r}: need distinct integers >= 0")
    return seeds
