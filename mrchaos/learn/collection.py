"""Where a run's data comes from: TorchRL collectors in this process, in worker processes or on Ray.

``collector.kind`` picks one of three TorchRL collectors over the same env factory:

- ``sync``: :class:`torchrl.collectors.Collector` over one env in the trainer's process;
- ``multisync``: :class:`torchrl.collectors.MultiSyncCollector`, ``workers`` processes on this machine;
- ``ray``: ``Collector(backend="ray")`` (TorchRL's ``RayCollector``), ``workers`` Ray actors on a
  local cluster or the one at ``collector.ray_address``.

Every worker gets its own seed stream (:func:`worker_seed`), its own thread budget
(``collector.worker_threads``: Ray's CPU reservation, MuJoCo's batch threads and torch's
threads) and the chaos cache by absolute path, built once by the trainer before the workers
start. The env always runs on the CPU; the policy runs on the run's device in this process
and in worker processes, and on the CPU in Ray actors (which reserve no GPU).

The curriculum stage reaches every worker inside the policy weights: the collector's policy
holds the trainer's :class:`~mrchaos.learn.curriculum.CurriculumStage`, and
:class:`CurriculumCollector` points each worker's curriculum transform at the copy that its
policy receives.
"""

from __future__ import annotations

import dataclasses
import functools
from pathlib import Path
from typing import Any

import torch
from tensordict.nn import TensorDictModuleBase
from torchrl.collectors import Collector, MultiSyncCollector
from torchrl.envs import TransformedEnv

from mrchaos.env.tangram import TangramEnv
from mrchaos.learn.config import ConfigError, TrainConfig
from mrchaos.learn.curriculum import CurriculumStage, CurriculumTransform

__all__ = [
    "CurriculumCollector",
    "collector_devices",
    "make_collector",
    "make_env",
    "worker_seed",
    "worker_config",
]

ENV_DEVICE = torch.device("cpu")


def worker_seed(seed: int, worker: int) -> int:
    """The env seed of collector worker ``worker`` (0-based) of a run seeded ``seed``.

    The trainer's own env (sync collection, evaluation) keeps ``seed``; workers take
    disjoint streams far from it, so that no two workers draw the same tasks."""
    return seed + 1000 * (worker + 1)


def make_env(cfg: TrainConfig, seed: int, stage: CurriculumStage | None = None) -> TransformedEnv:
    """The training env: batched tangram worlds on the CPU with the curriculum transform."""
    base = TangramEnv(cfg.env_config(), seed=seed, device=ENV_DEVICE)
    cur = CurriculumTransform(
        base.num_pieces, cfg.curriculum.stages, cfg.curriculum.window, cfg.curriculum.epsilon,
        cfg.curriculum.min_iters, seed=seed + 1, stage=stage,
    )
    return TransformedEnv(base, cur)


def worker_config(cfg: TrainConfig) -> TrainConfig:
    """The config a collector worker builds its env from: the chaos cache by absolute path
    (a worker may start in another folder) and MuJoCo on the worker's own threads."""
    task = cfg.task
    if task.cache.path:
        task = dataclasses.replace(task, cache=dataclasses.replace(task.cache, path=str(Path(task.cache.path).resolve())))
    physics = dataclasses.replace(cfg.env.physics, nthread=cfg.collector.worker_threads)
    return dataclasses.replace(cfg, task=task, env=dataclasses.replace(cfg.env, physics=physics))


def _worker_env(cfg: TrainConfig, seed: int, stage: CurriculumStage | None = None) -> TransformedEnv:
    # Runs inside the worker: its torch threads follow the CPUs it was given, and its policy
    # samples actions from the worker's own seed.
    torch.set_num_threads(max(1, cfg.collector.worker_threads))
    torch.manual_seed(seed)
    return make_env(cfg, seed, stage=stage)


def collector_devices(cfg: TrainConfig) -> dict[str, torch.device]:
    """The collector's devices: the env on the CPU; the policy and the stored batch on the run's
    device, except in Ray actors, which reserve no GPU and act on the CPU."""
    policy = ENV_DEVICE if cfg.collector.kind == "ray" else torch.device(cfg.device)
    return {"env_device": ENV_DEVICE, "policy_device": policy, "storing_device": policy}


def _find(root: Any, cls: type) -> Any | None:
    modules = root.modules() if isinstance(root, torch.nn.Module) else ()
    return next((m for m in modules if isinstance(m, cls)), None)


class CurriculumCollector(Collector):
    """TorchRL's single-process collector, with the env's curriculum following the stage that
    arrives in the policy weights (the class Ray instantiates in each actor)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        env = self.env
        transform = env.transform if isinstance(env, TransformedEnv) else None
        stage = _find(self.policy, CurriculumStage)
        if not isinstance(transform, CurriculumTransform) or stage is None:
            raise TypeError("CurriculumCollector needs a TransformedEnv with a CurriculumTransform and a policy "
                            "holding a CurriculumStage")
        transform.follow(stage)


def make_collector(cfg: TrainConfig, env: TransformedEnv, policy: TensorDictModuleBase,
                   stage: CurriculumStage) -> Any:
    """The run's collector (``cfg.collector.kind``), its policy weights already in every worker.

    Args:
        cfg: the experiment.
        env: the trainer's env (collected from with ``sync``; workers build their own).
        policy: the collection policy; it must hold ``stage`` as a submodule.
        stage: the trainer's curriculum stage (put in shared memory for worker processes).
    """
    kind = cfg.collector.kind
    if _find(policy, CurriculumStage) is not stage:
        raise ValueError("the collection policy must hold the trainer's CurriculumStage")
    common = {"frames_per_batch": cfg.collector.frames_per_batch, "total_frames": -1, **collector_devices(cfg)}
    if kind == "sync":
        return Collector(env, policy, auto_register_policy_transforms=False, **common)
    workers = cfg.collector.workers
    if cfg.collector.frames_per_batch % (workers * cfg.env.num_worlds):
        raise ValueError(f"collector.frames_per_batch ({cfg.collector.frames_per_batch}) must be a multiple of "
                         f"collector.workers x env.num_worlds ({workers} x {cfg.env.num_worlds})")
    wcfg = worker_config(cfg)
    if kind == "multisync":
        # Worker processes share the stage's memory with the trainer.
        stage.share_memory()
        factories = [functools.partial(_worker_env, wcfg, worker_seed(cfg.seed, i), stage) for i in range(workers)]
        return MultiSyncCollector(factories, policy, auto_register_policy_transforms=False, **common)
    return _ray_collector(cfg, wcfg, policy, common)


def _ray_collector(cfg: TrainConfig, wcfg: TrainConfig, policy: TensorDictModuleBase, common: dict) -> Any:
    try:
        import ray  # noqa: F401
    except ImportError:
        raise ConfigError("collector.kind: ray needs Ray: pip install -e '.[ray]'") from None
    c = cfg.collector
    threads = max(1, c.worker_threads)
    if c.ray_address:
        init = {"address": c.ray_address}
    else:
        init = {"num_cpus": c.workers * threads, "include_dashboard": False}
    # A worker's env draws tasks from its own seed; the stage comes with the policy weights.
    factories = [functools.partial(_worker_env, wcfg, worker_seed(cfg.seed, i)) for i in range(c.workers)]
    collector = Collector(
        factories, policy, backend="ray", num_collectors=c.workers, sync=True,
        backend_options={
            "collector_class": CurriculumCollector,
            "collector_kwargs": {"auto_register_policy_transforms": False},
            "ray_init_config": init,
            "remote_configs": {"num_cpus": threads, "num_gpus": 0},
        },
        **common,
    )
    # The actors were built from a pickled copy of the policy; send the weights (and the
    # stage) once before the first batch, as after every update.
    collector.update_policy_weights_()
    return collector
