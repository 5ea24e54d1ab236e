"""Training configuration: YAML files loaded into typed dataclasses, with dotted overrides.

    cfg = load_config("conf/full.yaml", ["optim.lr=1e-4", "env.num_worlds=64"])

An unknown key, a value of the wrong type or a missing file raises
:class:`ConfigError`, whose message names the file and lists the valid keys.
"""

from __future__ import annotations

import copy
import dataclasses
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
import yaml

from mrchaos.core.atomic import write_atomic
from mrchaos.core.errors import MrchaosError
from mrchaos.env.tangram import EnvConfig
from mrchaos.learn.policy import PolicyConfig
from mrchaos.learn.precision import PRECISIONS
from mrchaos.loggers.backends import check_backends
from mrchaos.tasks.presets import PRESETS, get_preset
from mrchaos.tasks.sampler import TaskConfig

__all__ = [
    "COLLECTOR_KINDS",
    "ConfigError",
    "CurriculumConfig",
    "CollectorConfig",
    "LossConfig",
    "OptimConfig",
    "LoggerConfig",
    "CheckpointConfig",
    "BCConfig",
    "ExitConfig",
    "RerankConfig",
    "TrainConfig",
    "ALGOS",
    "load_config",
    "config_from_dict",
    "upgrade_config_dict",
    "config_to_dict",
    "start_run",
]


#: Training algorithms: PPO (the method), supervision (BC, dense targets, DAgger, expert
#: iteration) and the afterstate re-ranker around a trained spatial policy.
ALGOS = ("ppo", "bc", "rerank")


class ConfigError(MrchaosError, ValueError):
    """A bad configuration file or override."""


@dataclass
class CurriculumConfig:
    """The two-stage curriculum.

    Attributes:
        stages: "both" (local then global), "local" (stage 1 only), "global" (stage 2 only).
        window: W, iterations over which stage-1 reward must improve.
        epsilon: the switch happens when the stage-1 reward has not improved by more
            than this over the last ``window`` iterations.
        min_iters: never switch before this many stage-1 iterations.
        max_minutes: with a fixed time budget, switch at the latest after this many
            minutes of training even if stage 1 still improves (0 = no cap).
    """

    stages: str = "both"
    window: int = 20
    epsilon: float = 0.01
    min_iters: int = 20
    max_minutes: float = 0.0

    def __post_init__(self) -> None:
        if self.stages not in ("both", "local", "global"):
            raise ValueError(f"curriculum.stages must be 'both', 'local' or 'global', got {self.stages!r}")


#: Collector backends (see :mod:`mrchaos.learn.collection`).
COLLECTOR_KINDS = ("sync", "multisync", "ray")


@dataclass
class CollectorConfig:
    """Data collection (see :mod:`mrchaos.learn.collection`).

    Attributes:
        frames_per_batch: world-steps per iteration, over all workers.
        total_frames: stop after this many (-1 = unbounded, stop on ``max_minutes``).
        max_minutes: stop after this many minutes of training (0 = no limit).
        kind: "sync" (one env in this process), "multisync" (``workers`` processes) or
            "ray" (``workers`` Ray actors).
        workers: collector workers of "multisync" and "ray", each with ``env.num_worlds`` worlds.
        worker_threads: CPUs per worker: Ray reserves them, and the worker's MuJoCo batch and
            torch use that many threads.
        ray_address: the Ray cluster to join ("auto", or "ray://host:10001"); unset, a local one
            starts with ``workers x worker_threads`` CPUs.
    """

    frames_per_batch: int = 2048
    total_frames: int = 2_000_000
    max_minutes: float = 0.0
    kind: str = "sync"
    workers: int = 2
    worker_threads: int = 1
    ray_address: str | None = None

    def __post_init__(self) -> None:
        if self.kind not in COLLECTOR_KINDS:
            raise ValueError(f"collector.kind must be one of {', '.join(COLLECTOR_KINDS)}, got {self.kind!r}")
        if self.workers < 1 or self.worker_threads < 1:
            raise ValueError(
                f"collector.workers and collector.worker_threads must be >= 1, got "
                f"{self.workers} and {self.worker_threads}"
            )


@dataclass
class LossConfig:
    """PPO: clipping, entropy and critic coefficients, GAE parameters, epochs and minibatches."""

    gamma: float = 0.99
    lmbda: float = 0.95
    clip_epsilon: float = 0.2
    entropy_coeff: float = 0.01
    critic_coeff: float = 0.5
    normalize_advantage: bool = True
    epochs: int = 3
    minibatch_size: int = 512


@dataclass
class OptimConfig:
    """Adam (the paper's learning rate), an optional linear anneal, and gradient clipping.

    ``lr_final`` anneals the learning rate linearly from ``lr`` to it as the run spends its
    budget: for PPO the larger of frames / ``collector.total_frames`` and minutes /
    ``collector.max_minutes``, for supervision (``algo: bc``) the planned epochs, DAgger
    rounds' included. None keeps ``lr`` constant (the paper's setting).
    """

    lr: float = 2e-4
    lr_final: float | None = None
    max_grad_norm: float = 0.5
    weight_decay: float = 0.0

    def learning_rate(self, progress: float) -> float:
        """The learning rate at ``progress`` (the budget's used fraction, clipped to [0, 1])."""
        if self.lr_final is None:
            return self.lr
        return self.lr + (self.lr_final - self.lr) * min(max(progress, 0.0), 1.0)


@dataclass
class LoggerConfig:
    """Where and how often to log.

    Every run writes ``metrics.csv`` (one row per iteration; ``--resume`` and ``mrchaos-plot``
    read it). ``backends`` adds loggers (:mod:`mrchaos.loggers.backends`): "rerun" (scalars,
    events and, every ``image_every`` iterations, ``image_worlds`` worlds' images), and
    TorchRL's "csv", "tensorboard", "wandb" and "mlflow" (scalars and the config). W&B and
    MLflow run offline unless ``online``; ``project`` names the W&B project and MLflow experiment.
    """

    backends: list[str] = field(default_factory=lambda: ["rerun"])
    online: bool = False
    project: str = "mrchaos"
    image_every: int = 20
    image_worlds: int = 4
    progress: bool = True

    def __post_init__(self) -> None:
        check_backends(self.backends)


@dataclass
class CheckpointConfig:
    """Save every ``every`` iterations and at the end; keep the last ``keep`` numbered ones."""

    every: int = 10
    keep: int = 3


@dataclass
class BCConfig:
    """Supervised learning from the simulator's answers: behaviour cloning and dense targets.

    Attributes:
        source: "figures" (the paper's BC: demonstrations of human figures, rotated and
            shifted) or "chaos" (demonstrations of chaos objects, the objects RL trains on).
        figure_sets: figures to demonstrate with ``source: figures`` ("builtin" = the library).
        rotations: rotate each figure by k * 360/rotations degrees, k < rotations.
        shifts: random shifts per rotation (plus the unshifted figure).
        max_shift: largest shift (m); figures that would leave the view are not shifted.
        objects: chaos objects demonstrated with ``source: chaos`` (drawn as ``task.chaos`` says).
        targets: "oracle" (the demonstrated grid action, negative log-likelihood) or "dense"
            (the counterfactual coverage of every grid action, a soft-target cross-entropy).
        temperature: dense targets are softmax(coverage / temperature) over the actions.
        overlap_limit: dense targets give no weight to actions whose footprint lies more than
            this share on pieces already placed (physics decides those).
        dagger_rounds: after the first fit, rounds in which the policy itself assembles new
            chaos objects and the states it reaches are labelled and added (DAgger).
        dagger_objects: chaos objects per DAgger round.
        dagger_epochs: passes over the aggregated data after each round.
        epochs: passes over the first demonstrations.
        minibatch_size: samples per gradient step.
        seed: seed of the demonstrated chaos objects (each DAgger round adds one).
    """

    source: str = "figures"
    figure_sets: list[str] = field(default_factory=lambda: ["builtin"])
    rotations: int = 8
    shifts: int = 3
    max_shift: float = 0.02
    objects: int = 6000
    targets: str = "oracle"
    temperature: float = 0.05
    overlap_limit: float = 0.02
    dagger_rounds: int = 0
    dagger_objects: int = 2000
    dagger_epochs: int = 3
    epochs: int = 20
    minibatch_size: int = 256
    seed: int = 778

    def __post_init__(self) -> None:
        if self.source not in ("figures", "chaos"):
            raise ValueError(f"bc.source must be 'figures' or 'chaos', got {self.source!r}")
        if self.targets not in ("oracle", "dense"):
            raise ValueError(f"bc.targets must be 'oracle' or 'dense', got {self.targets!r}")
        if self.temperature <= 0:
            raise ValueError(f"bc.temperature must be > 0, got {self.temperature}")


@dataclass
class ExitConfig:
    """Expert iteration: rounds in which the lookahead planner around the current policy
    assembles new chaos objects and the policy learns the planner's ranking of its candidates
    (:mod:`mrchaos.learn.planner`; the planner reads no solution). They follow the supervised
    rounds of ``bc`` (``bc.epochs: 0`` with ``init_from`` starts from another policy instead).

    Attributes:
        rounds: planner rounds (0 = none).
        objects: chaos objects the planner assembles per round (seeds ``bc.seed + 1000 + round``).
        k: candidates per step, the policy's own top-k (separate peaks under a mode window).
        temperature: the target over a state's candidates is softmax(IoU / temperature) of
            their completions' silhouette IoUs.
        weight: the ranking loss's weight.
        dense: the weight of the dense (or oracle) loss in the epochs of expert-iteration rounds
            (1 as in the supervised rounds; 0 learns the ranking alone, which did best on
            held-out chaos objects, docs/training.md).
        epochs: passes over the aggregated data after each round.
    """

    rounds: int = 0
    objects: int = 1000
    k: int = 5
    temperature: float = 0.01
    weight: float = 1.0
    dense: float = 1.0
    epochs: int = 2

    def __post_init__(self) -> None:
        if self.rounds < 0 or self.objects < 1 or self.epochs < 0:
            raise ValueError(
                f"exit.rounds and exit.epochs must be >= 0 and exit.objects >= 1, got "
                f"{self.rounds}, {self.epochs} and {self.objects}"
            )
        if self.k < 2:
            raise ValueError(f"exit.k must be >= 2 (a ranking needs two candidates), got {self.k}")
        if self.temperature <= 0 or self.weight < 0 or self.dense < 0:
            raise ValueError(
                f"exit.temperature must be > 0, exit.weight and exit.dense >= 0, got "
                f"{self.temperature}, {self.weight} and {self.dense}"
            )


@dataclass
class RerankConfig:
    """The afterstate re-ranker (``algo: rerank``, :mod:`mrchaos.learn.rerank`): a network that picks
    one of the spatial policy's top-k placements from the whole image, trained on the lookahead
    planner's judgement of those placements; the policy (``init_from``) stays as it is.

    Attributes:
        data: expert-iteration runs whose data shards (``data/round_R.pt``) hold the planner's
            judgement of each state's candidates.
        held_out: the last shards of ``data`` (by run, then round) kept for the held-out agreement
            (other chaos objects); 0 measures on the training states alone.
        k: candidates per step, the policy's top k; the planner of ``data`` must have kept as many.
        width: the re-ranker's convolution width.
        epochs: passes over the training states.
        lr: Adam's learning rate.
        batch: states per minibatch.
        temperature: the target over a state's candidates is softmax(IoU / temperature).
    """

    data: list[str] = field(default_factory=list)
    held_out: int = 1
    k: int = 5
    width: int = 32
    epochs: int = 3
    lr: float = 3.0e-4
    batch: int = 128
    temperature: float = 0.01

    def __post_init__(self) -> None:
        if self.k < 2 or self.width < 1 or self.epochs < 0 or self.batch < 1 or self.held_out < 0:
            raise ValueError(
                "rerank.k must be >= 2, rerank.width and rerank.batch >= 1, rerank.epochs and "
                f"rerank.held_out >= 0; got {self.k}, {self.width}, {self.batch}, {self.epochs}, {self.held_out}"
            )
        if self.lr <= 0 or self.temperature <= 0:
            raise ValueError(f"rerank.lr and rerank.temperature must be > 0, got {self.lr} and {self.temperature}")


@dataclass
class TrainConfig:
    """A whole experiment: ``algo`` "ppo" (the method) or "bc" (supervision: BC, dense targets, DAgger,
    expert iteration).

    ``precision`` "bf16" runs the network under bfloat16 autocast (see :mod:`mrchaos.learn.precision`);
    ``init_from`` starts the network from a checkpoint's weights (a shipped name, a run or a
    file), e.g. PPO on top of a supervised policy. ``compile`` runs it through ``torch.compile`` (a C++
    compiler on the machine; the first iterations pay the compilation)."""

    name: str = "run"
    algo: str = "ppo"
    seed: int = 0
    device: str = "cpu"
    precision: str = "fp32"
    compile: bool = False
    init_from: str | None = None
    threads: int = 2
    runs_dir: str = "runs"
    env: EnvConfig = field(default_factory=EnvConfig)
    task: TaskConfig = field(default_factory=TaskConfig)
    curriculum: CurriculumConfig = field(default_factory=CurriculumConfig)
    policy: PolicyConfig = field(default_factory=PolicyConfig)
    collector: CollectorConfig = field(default_factory=CollectorConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    logger: LoggerConfig = field(default_factory=LoggerConfig)
    checkpoint: CheckpointConfig = field(default_factory=CheckpointConfig)
    bc: BCConfig = field(default_factory=BCConfig)
    exit: ExitConfig = field(default_factory=ExitConfig)
    rerank: RerankConfig = field(default_factory=RerankConfig)

    def __post_init__(self) -> None:
        if self.algo not in ALGOS:
            raise ValueError(f"algo must be one of {ALGOS}, got {self.algo!r}")
        if self.precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {PRECISIONS}, got {self.precision!r}")
        no_budget = self.collector.total_frames <= 0 and self.collector.max_minutes <= 0
        if self.algo == "ppo" and self.optim.lr_final is not None and no_budget:
            raise ValueError(
                "optim.lr_final anneals over the run's budget: set collector.total_frames or collector.max_minutes"
            )
        if self.env.grid.refined and self.algo == "rerank":
            # The re-ranker's footprints are drawn at the coarse grid's poses.
            raise ValueError(
                "a refined grid (env.grid.fine_xy, fine_theta) trains with PPO, supervision or expert "
                "iteration; the re-ranker covers the coarse grid only"
            )
        if self.exit.rounds and self.algo != "bc":
            raise ValueError("exit.rounds are rounds of supervision: set algo: bc")
        if self.exit.rounds and self.policy.name != "spatial":
            raise ValueError("exit.rounds need the spatial policy (the planner ranks its grid actions)")
        if self.algo == "bc" and self.env.order == "free" and self.bc.targets != "dense":
            raise ValueError(
                "with env.order: free, supervision takes dense targets (bc.targets: dense): an oracle "
                "label would name one piece where several may go next"
            )

    def env_config(self) -> EnvConfig:
        """The env config with the task group folded in."""
        return dataclasses.replace(self.env, task=self.task)


#: Keys of earlier releases (flat env and task groups) and where they live now. Old YAML
#: files and the configs stored in old checkpoints load through :func:`upgrade_config_dict`.
RENAMED: dict[str, str] = {
    "env.view_extent": "env.view.extent",
    "env.view_size": "env.view.size",
    "env.grid_nx": "env.grid.nx",
    "env.grid_ny": "env.grid.ny",
    "env.grid_ntheta": "env.grid.ntheta",
    "env.grid_half_range": "env.grid.half_range",
    "env.view_mode": "env.observation.mode",
    "env.height_levels": "env.observation.levels",
    "env.robot_model": "env.robot.model",
    "env.settle_steps": "env.physics.settle_steps",
    "env.release_gap": "env.physics.release_gap",
    "env.push_depth": "env.physics.push_depth",
    "env.nthread": "env.physics.nthread",
    "env.twin_slots": "env.reward.twin_slots",
    "env.reward_shaping": "env.reward.shaping",
    "env.shaping_threshold": "env.reward.shaping_threshold",
    "env.penetration_gate": "env.reward.penetration_gate",
    "env.penetration_limit": "env.reward.penetration_limit",
    "env.angle_gate": "env.reward.angle_gate",
    "env.angle_tolerance_deg": "env.reward.angle_tolerance_deg",
    "env.action_noise_xy": "env.noise.action_xy",
    "env.action_noise_theta": "env.noise.action_theta",
    "env.camera_jitter": "env.noise.camera_jitter",
    "task.chaos": "task.mix.chaos",
    "task.cache": "task.mix.cache",
    "task.figures": "task.mix.figures",
    "task.chaos_mode": "task.chaos.mode",
    "task.attract_fraction": "task.chaos.attract_fraction",
    "task.angle_step": "task.chaos.angle_step",
    "task.workspace": "task.chaos.workspace",
    "task.cache_path": "task.cache.path",
    "task.cache_size": "task.cache.size",
    "task.cache_seed": "task.cache.seed",
    # Not an old key: the short spelling of the flip, whose home is the action grid it widens.
    "env.flip": "env.grid.flip",
}


def _get_dotted(data: dict, dotted: str) -> tuple[bool, Any]:
    node: Any = data
    for p in dotted.split("."):
        if not isinstance(node, dict) or p not in node:
            return False, None
        node = node[p]
    return True, node


def upgrade_config_dict(data: dict) -> dict:
    """A copy of a raw config dict with keys of earlier releases moved to their new homes.

    Old flat keys (``env.view_extent``) become nested ones (``env.view.extent``); an old
    ``task.chaos: 0.5`` or ``task.cache: 1.0`` (mix weights, numbers) are told from the new
    ``task.chaos`` and ``task.cache`` groups (mappings) by their type. A config of an old release that
    names no task preset gets the one whose piece sets hold its ``env.piece_set``. The old
    ``logger.rerun`` switch becomes ``logger.backends``.
    """
    data = copy.deepcopy(data)
    old_task = isinstance(data.get("task"), dict) and "preset" not in data["task"]
    for old, new in RENAMED.items():
        group, key = old.split(".")
        node = data.get(group)
        if not isinstance(node, dict) or key not in node:
            continue
        if isinstance(node[key], dict):
            continue  # task.chaos and task.cache: already the new groups (the old keys held numbers)
        value = node.pop(key)
        found, existing = _get_dotted(data, new)
        if found and existing != value:
            raise ConfigError(f"both '{old}' (an old key) and '{new}' are set; keep '{new}'")
        _set_dotted(data, new, value)
    logger = data.get("logger")
    if isinstance(logger, dict) and ("csv" in logger or "rerun" in logger):
        # Earlier releases had two switches; logger.csv was never read (metrics.csv is always written).
        logger.pop("csv", None)
        rerun = logger.pop("rerun", None)
        if rerun is not None:
            backends = [b for b in logger.get("backends", LoggerConfig().backends) if b != "rerun"]
            logger["backends"] = (["rerun"] if rerun else []) + backends
    piece_set = _get_dotted(data, "env.piece_set")[1]
    if (old_task or "task" not in data) and piece_set is not None:
        for name, preset in PRESETS.items():
            if piece_set == preset.piece_set or piece_set in preset.random_sets:
                data.setdefault("task", {})["preset"] = name
                break
    return data


def _merge_under(base: dict, top: dict) -> dict:
    """``top`` laid over ``base``, recursively: ``top``'s values win."""
    out = copy.deepcopy(base)
    for k, v in top.items():
        out[k] = _merge_under(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def _valid_keys(cls: type, prefix: str = "") -> list[str]:
    keys = []
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        t = hints[f.name]
        if dataclasses.is_dataclass(t) and not (cls is EnvConfig and f.name == "task"):
            keys.extend(_valid_keys(typing.cast(type, t), f"{prefix}{f.name}."))
        elif not (cls is EnvConfig and f.name == "task"):
            keys.append(f"{prefix}{f.name}")
    return keys


def _coerce(value: Any, t: Any, where: str) -> Any:
    origin = typing.get_origin(t)
    args = typing.get_args(t)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        for a in args:
            if a is type(None):
                continue
            try:
                return _coerce(value, a, where)
            except ConfigError:
                pass
        raise ConfigError(f"{where}: {value!r} is not a {t}")
    if origin is list:
        if not isinstance(value, list):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        return [_coerce(v, args[0] if args else Any, where) for v in value]
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        if args and args[-1] is not Ellipsis and len(value) != len(args):
            raise ConfigError(f"{where}: expected {len(args)} values, got {value!r}")
        types_ = [args[0]] * len(value) if args and args[-1] is Ellipsis else list(args) or [Any] * len(value)
        return tuple(_coerce(v, t_, where) for v, t_ in zip(value, types_, strict=True))
    if t is Any:
        return value
    if t is bool:
        if isinstance(value, bool):
            return value
        raise ConfigError(f"{where}: expected true/false, got {value!r}")
    if t is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where}: expected an integer, got {value!r}")
        return value
    if t is float:
        if isinstance(value, str):
            # YAML 1.1 reads 5e-5 (no dot) as a string; a number is what was meant.
            try:
                value = float(value)
            except ValueError:
                pass
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}: expected a number, got {value!r}")
        return float(value)
    if t is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected a string, got {value!r}")
        return value
    return value


def _build(cls: type, data: dict, where: str, prefix: str = "") -> Any:
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: {prefix or 'top level'} must be a mapping, got {data!r}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    kwargs = {}
    for key, value in data.items():
        if cls is EnvConfig and key == "task":
            raise ConfigError(f"{where}: put the task settings in the top-level 'task' group, not 'env.task'")
        if key not in names:
            raise ConfigError(
                f"{where}: unknown key '{prefix}{key}'. Valid keys: {', '.join(_valid_keys(cls, prefix))}"
            )
        t = hints[key]
        if dataclasses.is_dataclass(t):
            kwargs[key] = _build(typing.cast(type, t), value or {}, where, f"{prefix}{key}.")
        else:
            kwargs[key] = _coerce(value, t, f"{where}: {prefix}{key}")
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as e:
        raise ConfigError(f"{where}: {e}") from None


def _set_dotted(data: dict, dotted: str, value: Any) -> None:
    parts = dotted.split(".")
    node = data
    for p in parts[:-1]:
        node = node.setdefault(p, {})
        if not isinstance(node, dict):
            raise ConfigError(f"override {dotted}: '{p}' is not a group")
    node[parts[-1]] = value


def load_config(path: str | Path | None, overrides: list[str] | None = None) -> TrainConfig:
    """Load a YAML experiment (or the defaults when ``path`` is None) and apply ``key=value`` overrides."""
    data: dict = {}
    where = str(path) if path else "<defaults>"
    if path is not None:
        p = Path(path)
        if not p.exists():
            raise ConfigError(f"{p}: no such config file")
        try:
            data = yaml.safe_load(p.read_text()) or {}
        except yaml.YAMLError as e:
            raise ConfigError(f"{p}: not valid YAML ({e})") from None
        if not isinstance(data, dict):
            raise ConfigError(f"{p}: the top level must be a mapping, got {data!r}")
    return config_from_dict(data, where, overrides)


def config_from_dict(data: dict, where: str = "<dict>", overrides: list[str] | None = None) -> TrainConfig:
    """A :class:`TrainConfig` from a raw nested dict: old keys moved, ``key=value`` overrides applied,
    the task preset laid underneath."""
    data = upgrade_config_dict(data)
    for ov in overrides or []:
        if "=" not in ov:
            raise ConfigError(f"override {ov!r}: expected key=value")
        key, raw = ov.split("=", 1)
        try:
            value = yaml.safe_load(raw)
        except yaml.YAMLError:
            value = raw
        key = key.strip()
        if key in RENAMED and not isinstance(value, dict):
            key = RENAMED[key]
        _set_dotted(data, key, value)
    if overrides:
        where = f"{where} (with overrides)"
        data = upgrade_config_dict(data)  # an override may use an old key too (logger.rerun=false)
    task = data.get("task") or {}
    name = task.get("preset", TaskConfig.preset) if isinstance(task, dict) else TaskConfig.preset
    try:
        preset = get_preset(name)
    except KeyError as e:
        raise ConfigError(f"{where}: task.preset: {e.args[0]}") from None
    return _build(TrainConfig, _merge_under(preset.config_overrides(), data), where)


def _plain(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


def config_to_dict(cfg: Any) -> dict:
    """Plain-dict form of a config (for YAML and checkpoints; tuples become lists)."""
    d = _plain(dataclasses.asdict(cfg))
    if isinstance(cfg, TrainConfig):
        d["env"].pop("task", None)
    return d


def start_run(cfg: TrainConfig, run_dir: Path, resume: bool = False) -> Path:
    """Open a run folder for an epoch-checkpointed run: ``checkpoints/`` made, the resolved config
    written as ``config.yaml`` (when resuming, rewritten only if overrides changed it, so that the
    file says what the rest of the run does), torch's threads and seed set from the config; returns
    the path of ``checkpoints/last.pt``."""
    (run_dir / "checkpoints").mkdir(parents=True, exist_ok=True)
    text = yaml.safe_dump(config_to_dict(cfg), sort_keys=False)
    path = run_dir / "config.yaml"
    if not resume or not path.exists() or yaml.safe_load(path.read_text()) != yaml.safe_load(text):
        write_atomic(path, text)
    torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    return run_dir / "checkpoints" / "last.pt"
