"""Training configuration: YAML files loaded into typed dataclasses, with dotted overrides.

    cfg = load_config("conf/full.yaml", ["optim.lr=1e-4", "env.num_worlds=64"])

An unknown key, a value of the wrong type or a missing file raises
:class:`ConfigError`, whose message names the file and lists the valid keys.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from mrchaos.bc import BCConfig
from mrchaos.env import EnvConfig
from mrchaos.errors import MrchaosError
from mrchaos.policy import PolicyConfig
from mrchaos.task import TaskConfig

__all__ = [
    "ConfigError",
    "CurriculumConfig",
    "CollectorConfig",
    "LossConfig",
    "OptimConfig",
    "LoggerConfig",
    "CheckpointConfig",
    "TrainConfig",
    "load_config",
    "config_to_dict",
]


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


@dataclass
class CollectorConfig:
    """Data collection: ``frames_per_batch`` world-steps per iteration, ``total_frames`` in all
    (-1 = unbounded, stop on ``max_minutes``), ``kind`` "sync" (one env in this process) or
    "multisync" (``workers`` processes)."""

    frames_per_batch: int = 2048
    total_frames: int = 2_000_000
    max_minutes: float = 0.0
    kind: str = "sync"
    workers: int = 2


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
    """Adam (the paper's learning rate) and gradient clipping."""

    lr: float = 2e-4
    max_grad_norm: float = 0.5
    weight_decay: float = 0.0


@dataclass
class LoggerConfig:
    """Where and how often to log: CSV every iteration, rerun images every ``image_every`` iterations."""

    csv: bool = True
    rerun: bool = True
    image_every: int = 20
    image_worlds: int = 4
    progress: bool = True


@dataclass
class CheckpointConfig:
    """Save every ``every`` iterations and at the end; keep the last ``keep`` numbered ones."""

    every: int = 10
    keep: int = 3


@dataclass
class TrainConfig:
    """A whole experiment: ``algo`` "ppo" (the method) or "bc" (behaviour cloning, the baseline)."""

    name: str = "run"
    algo: str = "ppo"
    seed: int = 0
    device: str = "cpu"
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

    def __post_init__(self) -> None:
        if self.algo not in ("ppo", "bc"):
            raise ValueError(f"algo must be 'ppo' or 'bc', got {self.algo!r}")

    def env_config(self) -> EnvConfig:
        """The env config with the task group folded in."""
        return dataclasses.replace(self.env, task=self.task)


def _valid_keys(cls: type, prefix: str = "") -> list[str]:
    keys = []
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        t = hints[f.name]
        if dataclasses.is_dataclass(t) and not (cls is EnvConfig and f.name == "task"):
            keys.extend(_valid_keys(t, f"{prefix}{f.name}."))
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
            kwargs[key] = _build(t, value or {}, where, f"{prefix}{key}.")
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
    for ov in overrides or []:
        if "=" not in ov:
            raise ConfigError(f"override {ov!r}: expected key=value")
        key, raw = ov.split("=", 1)
        try:
            value = yaml.safe_load(raw)
        except yaml.YAMLError:
            value = raw
        _set_dotted(data, key.strip(), value)
        where = f"{where} (with overrides)"
    return _build(TrainConfig, data, where)


def config_to_dict(cfg: Any) -> dict:
    """Plain-dict form of a config (for YAML and checkpoints)."""
    d = dataclasses.asdict(cfg)
    if isinstance(cfg, TrainConfig):
        d["env"].pop("task", None)
    return d
