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

The curriculum stage reaches every worker: worker processes share the memory of the
trainer's curriculum stage tensor; Ray actors, which share no
memory with the trainer, get it from :func:`publish_stage` (TorchRL's ``map_fn`` on each
:class:`CurriculumCollector`) before their next batch, as the policy weights.
"""

from __future__ import annotations

import dataclasses
import functools
import sys
from pathlib import Path
from typing import Any

import torch
from tensordict.nn import TensorDictModuleBase
from torchrl.collectors import Collector, MultiSyncCollector
from torchrl.envs import TransformedEnv

from mrchaos.env.tangram import TangramEnv
from mrchaos.learn.config import ConfigError, TrainConfig
from mrchaos.learn.curriculum import CurriculumTransform

__all__ = [
    "CurriculumCollector",
    "collector_devices",
    "make_collector",
    "make_env",
    "prepare_weights",
    "publish_stage",
    "worker_seed",
    "worker_config",
]

ENV_DEVICE = torch.device("cpu")


def worker_seed(seed: int, worker: int) -> int:
    """The env seed of collector worker ``worker`` (0-based) of a run seeded ``seed``.

    The trainer's own env (sync collection, evaluation) keeps ``seed``; workers take
    disjoint streams far from it, so that no two workers draw the same tasks."""
    return seed + 1000 * (worker + 1)


def make_env(cfg: TrainConfig, seed: int, stage: torch.Tensor | None = None) -> TransformedEnv:
    """The training env: batched tangram worlds on the CPU with the curriculum transform."""
    base = TangramEnv(cfg.env_config(), seed=seed, device=ENV_DEVICE)
    cur = CurriculumTransform(
        base.num_pieces,
        cfg.curriculum.stages,
        cfg.curriculum.window,
        cfg.curriculum.epsilon,
        cfg.curriculum.min_iters,
        seed=seed + 1,
        stage=stage,
    )
    return TransformedEnv(base, cur)


def worker_config(cfg: TrainConfig) -> TrainConfig:
    """The config a collector worker builds its env from: the chaos cache by absolute path
    (a worker may start in another folder) and MuJoCo on the worker's own threads."""
    task = cfg.task
    if task.cache.path:
        cache = dataclasses.replace(task.cache, path=str(Path(task.cache.path).resolve()))
        task = dataclasses.replace(task, cache=cache)
    physics = dataclasses.replace(cfg.env.physics, nthread=cfg.collector.worker_threads)
    return dataclasses.replace(cfg, task=task, env=dataclasses.replace(cfg.env, physics=physics))


def _worker_env(cfg: TrainConfig, seed: int, stage: torch.Tensor | None = None) -> TransformedEnv:
    # Runs inside the worker: its torch threads follow the CPUs it was given, and its policy
    # samples actions from the worker's own seed.
    torch.set_num_threads(cfg.collector.worker_threads)
    torch.manual_seed(seed)
    return make_env(cfg, seed, stage=stage)


def prepare_weights(cfg: TrainConfig, module: torch.nn.Module) -> None:
    """Lay the weights out as the collector's weight transport needs, in place (before the
    optimiser sees them): Ray sends them over Gloo, which takes only contiguous tensors, and
    the spatial net keeps its convolution weights channels-last."""
    if cfg.collector.kind == "ray":
        for t in [*module.parameters(), *module.buffers()]:
            if not t.is_contiguous():
                t.data = t.data.contiguous()


def collector_devices(cfg: TrainConfig) -> dict[str, torch.device]:
    """The collector's devices: the env on the CPU; the policy and the stored batch on the run's
    device, except in Ray actors, which reserve no GPU and act on the CPU."""
    policy = ENV_DEVICE if cfg.collector.kind == "ray" else torch.device(cfg.device)
    return {"env_device": ENV_DEVICE, "policy_device": policy, "storing_device": policy}


def _find(root: Any, cls: type) -> Any | None:
    modules = root.modules() if isinstance(root, torch.nn.Module) else ()
    return next((m for m in modules if isinstance(m, cls)), None)


class CurriculumCollector(Collector):
    """TorchRL's single-process collector with a handle on its env's curriculum (the class Ray
    instantiates in each actor, so that the trainer can set the stage there)."""

    def set_curriculum_stage(self, stage: int) -> int:
        """Set the stage of this collector's env (later resets follow it); returns it."""
        env, transform = self.env, None
        # The collector may have wrapped the env in transforms of its own.
        while transform is None and isinstance(env, TransformedEnv):
            transform, env = _find(env.transform, CurriculumTransform), env.base_env
        if transform is None:
            raise TypeError("CurriculumCollector's env has no CurriculumTransform")
        transform.stage.fill_(int(stage))
        return int(transform.stage)


def publish_stage(collector: Any, stage: torch.Tensor) -> None:
    """Send the trainer's curriculum stage to Ray actors (worker processes share its memory,
    and a sync collector's env reads it directly)."""
    if hasattr(collector, "remote_collectors"):
        got = collector.map_fn("set_curriculum_stage", [(int(stage),)] * collector.num_workers)
        if set(got) != {int(stage)}:
            raise RuntimeError(f"Ray actors report curriculum stages {got}, expected {int(stage)}")


def make_collector(cfg: TrainConfig, env: TransformedEnv, policy: TensorDictModuleBase, stage: torch.Tensor) -> Any:
    """The run's collector (``cfg.collector.kind``), its policy weights already in every worker.

    Args:
        cfg: the experiment.
        env: the trainer's env (collected from with ``sync``; workers build their own).
        policy: the collection policy.
        stage: the trainer's curriculum stage (put in shared memory for worker processes).
    """
    kind = cfg.collector.kind
    common = {"frames_per_batch": cfg.collector.frames_per_batch, "total_frames": -1, **collector_devices(cfg)}
    if kind == "sync":
        return Collector(env, policy, auto_register_policy_transforms=False, **common)
    workers = cfg.collector.workers
    if cfg.collector.frames_per_batch % (workers * cfg.env.num_worlds):
        raise ValueError(
            f"collector.frames_per_batch ({cfg.collector.frames_per_batch}) must be a multiple of "
            f"collector.workers x env.num_worlds ({workers} x {cfg.env.num_worlds})"
        )
    wcfg = worker_config(cfg)
    if kind == "multisync":
        # Worker processes share the stage's memory with the trainer.
        stage.share_memory_()
        factories = [functools.partial(_worker_env, wcfg, worker_seed(cfg.seed, i), stage) for i in range(workers)]
        return MultiSyncCollector(factories, policy, auto_register_policy_transforms=False, **common)
    return _ray_collector(cfg, wcfg, policy, stage, common)


def _ray_collector(
    cfg: TrainConfig, wcfg: TrainConfig, policy: TensorDictModuleBase, stage: torch.Tensor, common: dict
) -> Any:
    try:
        import ray  # noqa: F401
    except ImportError:
        raise ConfigError("collector.kind: ray needs Ray: pip install -e '.[ray]'") from None
    c = cfg.collector
    threads = c.worker_threads
    if c.ray_address:
        init: dict[str, Any] = {"address": c.ray_address}
    else:
        init = {"num_cpus": c.workers * threads, "include_dashboard": False}
    # A worker's env draws tasks from its own seed; the stage comes from publish_stage.
    factories = [functools.partial(_worker_env, wcfg, worker_seed(cfg.seed, i)) for i in range(c.workers)]
    # RayCollector reads total_frames=-1 literally (no batch); the trainer decides when to stop.
    common = {**common, "total_frames": sys.maxsize}
    collector = Collector(
        factories,
        policy,
        backend="ray",
        num_collectors=c.workers,
        sync=True,
        backend_options={
            "collector_class": CurriculumCollector,
            "collector_kwargs": {"auto_register_policy_transforms": False},
            "ray_init_config": init,
            "remote_configs": {"num_cpus": threads, "num_gpus": 0},
        },
        **common,
    )
    # The actors were built from a pickled copy of the policy and their own stage: send the
    # weights and the stage (a resumed run may be in stage 2) before the first batch.
    collector.update_policy_weights_()
    publish_stage(collector, stage)
    return collector
