"""PPO training with the two-stage curriculum, from TorchRL parts.

Collector → GAE → ClipPPOLoss → Adam, read top to bottom in :meth:`Trainer.run`.
A run lives in ``runs/<name>/``: the resolved ``config.yaml``, ``metrics.csv``,
``recording.rrd``, ``checkpoints/`` (``last.pt`` plus numbered ones) and, at the
end, ``eval.json`` (greedy policy on seeded Random objects).
"""

from __future__ import annotations

import csv
import json
import logging
import math
import signal
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml
from tensordict import TensorDict
from tensordict.nn import TensorDictSequential
from torchrl.collectors import Collector, MultiSyncCollector
from torchrl.data import LazyTensorStorage, ReplayBuffer, SamplerWithoutReplacement
from torchrl.envs import TransformedEnv
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE

from mrchaos.checkpoint import CheckpointError, check_compatible, load_checkpoint, save_checkpoint
from mrchaos.config import TrainConfig, config_to_dict, load_config
from mrchaos.curriculum import GLOBAL, LOCAL, CurriculumTransform
from mrchaos.env import TangramEnv
from mrchaos.figure_io import write_atomic
from mrchaos.policy import build_actor_critic

__all__ = ["Trainer", "make_env", "evaluate_random"]

log = logging.getLogger("mrchaos.train")

CSV_FIELDS = [
    "iteration", "frames", "episodes", "minutes", "sps", "stage", "reward", "rela", "final",
    "loss_objective", "loss_critic", "loss_entropy", "entropy", "collect_s", "update_s",
]


def make_env(cfg: TrainConfig, seed: int, stage: torch.Tensor | None = None) -> TransformedEnv:
    """The training env: batched tangram worlds with the curriculum transform."""
    base = TangramEnv(cfg.env_config(), seed=seed, device=cfg.device)
    cur = CurriculumTransform(
        base.num_pieces, cfg.curriculum.stages, cfg.curriculum.window, cfg.curriculum.epsilon,
        cfg.curriculum.min_iters, seed=seed + 1, stage=stage,
    )
    return TransformedEnv(base, cur)


def evaluate_random(policy, cfg: TrainConfig, n: int = 200, seed: int = 2024) -> dict[str, float]:
    """Greedy whole-episode evaluation on ``n`` seeded Random (chaos) objects."""
    import dataclasses

    from mrchaos.chaos import generate
    from mrchaos.evaluate import evaluate, policy_actor

    task = dataclasses.replace(cfg.task, chaos=1.0, cache=0.0, figures=0.0)
    env_cfg = dataclasses.replace(cfg.env_config(), task=task, num_worlds=min(n, 100), action_noise_xy=0.0,
                                  action_noise_theta=0.0, camera_jitter=0.0)
    env = TangramEnv(env_cfg, seed=seed)
    targets = generate(env.piece_set, n, np.random.default_rng(seed), cfg.task.chaos_config(env_cfg.view_extent))[0]
    res = evaluate(env, targets, policy_actor(policy))
    return {"n": n, "rela": float(res.rela.mean()), "final": float(res.final.mean()),
            "iou": float(res.iou.mean()), "strict_rela": float(res.strict_rela.mean())}


class Trainer:
    """One training run.

    Args:
        cfg: the experiment.
        run_dir: output folder (created).
        resume: continue from ``run_dir/checkpoints/last.pt``.
    """

    def __init__(self, cfg: TrainConfig, run_dir: Path, resume: bool = False) -> None:
        self.cfg = cfg
        self.run_dir = Path(run_dir)
        self.ckpt_dir = self.run_dir / "checkpoints"
        self.ckpt_dir.mkdir(parents=True, exist_ok=True)
        torch.set_num_threads(cfg.threads)
        torch.manual_seed(cfg.seed)
        self.stop_requested = False

        n = cfg.env.num_worlds
        if cfg.collector.frames_per_batch % n:
            raise ValueError(f"collector.frames_per_batch ({cfg.collector.frames_per_batch}) must be a multiple "
                             f"of env.num_worlds ({n})")
        # The stage lives in shared memory so that collector workers follow the switch.
        self.stage = torch.tensor(GLOBAL if cfg.curriculum.stages == "global" else LOCAL).share_memory_()
        self.env = make_env(cfg, cfg.seed, stage=self.stage)
        self.curriculum: CurriculumTransform = self.env.transform
        base: TangramEnv = self.env.base_env
        self.base = base
        self.actor_critic = build_actor_critic(cfg.policy, base.grid, base.view, base.action_spec).to(cfg.device)
        self.policy = self.actor_critic.get_policy_operator()
        self.value = self.actor_critic.get_value_operator()
        # What the collector stores: the action and its log-probability, not the
        # intermediate features and logits (for the spatial net, gigabytes per batch).
        self.collect_policy = TensorDictSequential(self.policy, selected_out_keys=["action", "action_log_prob"])
        # No vmap: the spatial trunk uses channels_last tensors, which vmap cannot query.
        self.advantage = GAE(
            gamma=cfg.loss.gamma, lmbda=cfg.loss.lmbda, value_network=self.value, average_gae=False, deactivate_vmap=True
        )
        # The critic gets only its head: the actor's pass has already written the shared
        # trunk's output, so the trunk runs once per minibatch instead of twice.
        self.loss = ClipPPOLoss(
            self.policy, self.actor_critic.get_value_head(), clip_epsilon=cfg.loss.clip_epsilon,
            entropy_coeff=cfg.loss.entropy_coeff,
            critic_coeff=cfg.loss.critic_coeff, normalize_advantage=cfg.loss.normalize_advantage,
            loss_critic_type="smooth_l1",
        )
        self.optim = torch.optim.Adam(self.loss.parameters(), lr=cfg.optim.lr, weight_decay=cfg.optim.weight_decay)
        self.buffer = ReplayBuffer(
            storage=LazyTensorStorage(cfg.collector.frames_per_batch),
            sampler=SamplerWithoutReplacement(),
            batch_size=cfg.loss.minibatch_size,
        )
        self.iteration = 0
        self.frames = 0
        self.episodes = 0
        self.minutes = 0.0
        if resume:
            self._restore(self.ckpt_dir / "last.pt")
        self.collector = self._make_collector()
        self.csv_path = self.run_dir / "metrics.csv"
        if resume and self.csv_path.exists():
            self._truncate_metrics()
        self.rerun = None
        if cfg.logger.rerun:
            from mrchaos.rerun_logger import RerunLogger

            name = "recording.rrd" if not resume else f"recording.resume{self.iteration}.rrd"
            self.rerun = RerunLogger(cfg.name, str(self.run_dir), file_name=name)
            self.rerun.log_hparams(config_to_dict(cfg))

    # ------------------------------------------------------------------ parts
    def _make_collector(self):
        cfg = self.cfg
        if cfg.collector.kind == "multisync":
            stage = self.stage

            def factory(cfg=cfg, stage=stage):
                return make_env(cfg, cfg.seed + 1000, stage=stage)

            return MultiSyncCollector(
                [factory] * cfg.collector.workers, self.collect_policy,
                frames_per_batch=cfg.collector.frames_per_batch, total_frames=-1,
                auto_register_policy_transforms=False,
            )
        if cfg.collector.kind != "sync":
            raise ValueError(f"collector.kind must be 'sync' or 'multisync', got {cfg.collector.kind!r}")
        return Collector(
            self.env, self.collect_policy, frames_per_batch=cfg.collector.frames_per_batch, total_frames=-1,
            auto_register_policy_transforms=False,
        )

    def state(self) -> dict[str, Any]:
        """Everything a resume needs (tensors and builtin containers only)."""
        base = self.base
        return {
            "kind": "mrchaos-policy",
            "config": config_to_dict(self.cfg),
            "policy": config_to_dict(self.cfg.policy),
            "piece_set": base.piece_set.name,
            "obs_shape": [2, base.view.size, base.view.size],
            "grid": list(base.grid.nvec),
            "view_extent": base.view.extent,
            "model": self.actor_critic.state_dict(),
            "optim": self.optim.state_dict(),
            "curriculum": {
                "stage": int(self.curriculum.stage), "switched_at": int(self.curriculum.switched_at),
                **self.curriculum.extra_state(),
            },
            "rng": {
                "torch": torch.get_rng_state(),
                "env": base.rng.get_state(),
                "env_np": base._np_rng.bit_generator.state,
            },
            "iteration": self.iteration,
            "frames": self.frames,
            "episodes": self.episodes,
            "minutes": self.minutes,
        }

    def _restore(self, path: Path) -> None:
        st = load_checkpoint(path)
        check_compatible(st, path, self.base.piece_set.name, [2, self.base.view.size, self.base.view.size],
                         self.base.grid.nvec)
        try:
            self.actor_critic.load_state_dict(st["model"])
            self.optim.load_state_dict(st["optim"])
        except (RuntimeError, KeyError, ValueError) as e:
            raise CheckpointError(f"{path}: weights do not fit this policy config ({str(e)[:200]})") from None
        cur = st["curriculum"]
        self.curriculum.stage.fill_(cur["stage"])
        self.curriculum.switched_at.fill_(cur["switched_at"])
        self.curriculum.load_extra_state(cur)
        torch.set_rng_state(st["rng"]["torch"])
        self.base.rng.set_state(st["rng"]["env"])
        self.base._np_rng.bit_generator.state = st["rng"]["env_np"]
        self.iteration, self.frames = st["iteration"], st["frames"]
        self.episodes, self.minutes = st["episodes"], st["minutes"]
        log.info("resumed %s at iteration %d, %d frames, stage %d", path, self.iteration, self.frames, cur["stage"])

    def save(self) -> Path:
        """Write ``last.pt`` and a numbered checkpoint (keeping the newest ``checkpoint.keep``)."""
        state = self.state()
        numbered = self.ckpt_dir / f"iter{self.iteration:06d}.pt"
        save_checkpoint(numbered, state)
        save_checkpoint(self.ckpt_dir / "last.pt", state)
        old = sorted(self.ckpt_dir.glob("iter*.pt"))[: -max(1, self.cfg.checkpoint.keep)]
        for p in old:
            p.unlink(missing_ok=True)
        return numbered

    def _request_stop(self, signum, frame) -> None:
        log.warning("signal %d: saving and stopping after this iteration", signum)
        self.stop_requested = True

    # ------------------------------------------------------------------ logging
    def _truncate_metrics(self) -> None:
        """Drop rows of iterations after the checkpoint (a killed run redoes them)."""
        with open(self.csv_path, newline="") as f:
            rows = list(csv.DictReader(f))
        keep = [r for r in rows if int(r["iteration"]) <= self.iteration]
        if len(keep) < len(rows):
            lines = [",".join(CSV_FIELDS)] + [",".join(str(r.get(k, "")) for k in CSV_FIELDS) for r in keep]
            write_atomic(self.csv_path, "\n".join(lines) + "\n")

    def _log(self, row: dict[str, Any], data: TensorDict) -> None:
        new = not self.csv_path.exists()
        with open(self.csv_path, "a", newline="") as f:
            w = csv.DictWriter(f, fieldnames=CSV_FIELDS)
            if new:
                w.writeheader()
            w.writerow({k: row.get(k, "") for k in CSV_FIELDS})
        if self.rerun is not None:
            for k in ("reward", "rela", "final", "loss_objective", "loss_critic", "loss_entropy", "entropy", "stage",
                      "sps"):
                v = row.get(k)
                if v is not None and not (isinstance(v, float) and math.isnan(v)):
                    self.rerun.log_scalar(k, v, step=self.iteration)
            every = max(1, self.cfg.logger.image_every)
            if self.iteration % every == 1 or every == 1:
                data = data.reshape(-1, data.shape[-1])  # (worlds, time), also for multi-process batches
                k = min(self.cfg.logger.image_worlds, data.shape[0])
                self.rerun.log_worlds(
                    self.iteration, data["observation"][:k, -1].numpy(), data["action"][:k, -1].numpy(),
                    data["next", "reward"][:k, -1, 0].numpy(), (self.base.grid.xs, self.base.grid.ys),
                    self.base.view.extent,
                )

    # ------------------------------------------------------------------ loop
    def run(self) -> dict[str, Any]:
        cfg = self.cfg
        write_atomic(self.run_dir / "config.yaml", yaml.safe_dump(config_to_dict(cfg), sort_keys=False))
        old_handlers = {s: signal.signal(s, self._request_stop) for s in (signal.SIGINT, signal.SIGTERM)}
        bar = None
        if cfg.logger.progress:
            from tqdm import tqdm

            total = cfg.collector.total_frames if cfg.collector.total_frames > 0 else None
            bar = tqdm(total=total, initial=self.frames, unit="f", dynamic_ncols=True)
        started = time.perf_counter() - self.minutes * 60
        t_collect = time.perf_counter()
        try:
            for data in self.collector:
                collect_s = time.perf_counter() - t_collect
                t_update = time.perf_counter()
                self.iteration += 1
                self.frames += data.numel()
                done = data["next", "done"][..., 0]
                self.episodes += int(done.sum())
                acted = data["next", "info", "piece"][..., 0] >= 0
                step_cov = data["next", "info", "step_coverage"][..., 0][acted]
                finals = data["next", "info", "final"][..., 0][done]
                reward = float(data["next", "reward"].mean())

                # PPO: advantages once per batch, then epochs of minibatches.
                with torch.no_grad():
                    self.advantage(data)
                self.buffer.empty()
                self.buffer.extend(data.reshape(-1))
                sums = {"loss_objective": 0.0, "loss_critic": 0.0, "loss_entropy": 0.0, "entropy": 0.0}
                n_mb = max(1, cfg.collector.frames_per_batch // cfg.loss.minibatch_size)
                for _ in range(cfg.loss.epochs):
                    for _ in range(n_mb):
                        batch = self.buffer.sample()
                        out = self.loss(batch)
                        total = out["loss_objective"] + out["loss_critic"] + out["loss_entropy"]
                        self.optim.zero_grad(set_to_none=True)
                        total.backward()
                        torch.nn.utils.clip_grad_norm_(self.loss.parameters(), cfg.optim.max_grad_norm)
                        self.optim.step()
                        for k in sums:
                            sums[k] += float(out[k].detach()) / (cfg.loss.epochs * n_mb)
                self.collector.update_policy_weights_()

                stage = int(self.curriculum.stage)
                self.minutes = (time.perf_counter() - started) / 60
                cap = cfg.curriculum.max_minutes
                plateau = stage == LOCAL and self.curriculum.update(self.iteration, reward)
                capped = not plateau and stage == LOCAL and 0 < cap <= self.minutes and \
                    self.curriculum.force_switch(self.iteration)
                if plateau or capped:
                    self.stage.fill_(int(self.curriculum.stage))
                    why = "stage-1 reward plateaued" if plateau else f"time cap of {cap:g} min"
                    msg = f"curriculum: stage 1 -> 2 at iteration {self.iteration} ({self.frames} frames; {why})"
                    log.info(msg)
                    if self.rerun is not None:
                        self.rerun.log_text("events", msg, step=self.iteration)
                update_s = time.perf_counter() - t_update
                row = {
                    "iteration": self.iteration, "frames": self.frames, "episodes": self.episodes,
                    "minutes": round(self.minutes, 3), "sps": data.numel() / (collect_s + update_s),
                    "stage": stage, "reward": reward,
                    "rela": float(step_cov.mean()) if len(step_cov) else float("nan"),
                    "final": float(finals.mean()) if len(finals) else float("nan"),
                    "collect_s": round(collect_s, 3), "update_s": round(update_s, 3), **sums,
                }
                self._log(row, data)
                if bar is not None:
                    bar.update(data.numel())
                    bar.set_postfix(sps=f"{row['sps']:.0f}", reward=f"{reward:.3f}", rela=f"{row['rela']:.3f}",
                                    stage=stage, refresh=False)
                if self.iteration % max(1, cfg.checkpoint.every) == 0:
                    self.save()
                over_frames = 0 < cfg.collector.total_frames <= self.frames
                over_time = 0 < cfg.collector.max_minutes <= self.minutes
                if over_frames or over_time or self.stop_requested:
                    break
                t_collect = time.perf_counter()
        finally:
            for s, h in old_handlers.items():
                signal.signal(s, h)
            if bar is not None:
                bar.close()
            self.collector.shutdown()
            self.save()
            if self.rerun is not None:
                self.rerun.close()
        return {"iteration": self.iteration, "frames": self.frames, "stopped": self.stop_requested}

    def finish(self, n_eval: int = 200) -> dict[str, float]:
        """Greedy evaluation on Random objects, written to ``eval.json``."""
        res = evaluate_random(self.policy, self.cfg, n=n_eval)
        write_atomic(self.run_dir / "eval.json", json.dumps(res, indent=1) + "\n")
        return res


def resume_config(run_dir: Path) -> TrainConfig:
    """The config a run was started with (its ``config.yaml``)."""
    path = Path(run_dir) / "config.yaml"
    if not path.exists():
        raise FileNotFoundError(f"{run_dir}: not a run directory (no config.yaml)")
    return load_config(path)
