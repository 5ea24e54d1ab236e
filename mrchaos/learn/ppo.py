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
import signal
import time
from pathlib import Path
from typing import Any

import torch
import yaml
from tensordict import TensorDict
from tensordict.nn import TensorDictSequential
from torchrl.data import LazyTensorStorage, ReplayBuffer, SamplerWithoutReplacement
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE

from mrchaos.core.atomic import write_atomic
from mrchaos.env.rewards import REWARD_TERMS
from mrchaos.env.tangram import TangramEnv
from mrchaos.learn.checkpoint import (
    CheckpointError,
    checkpoint_path,
    load_weights,
    policy_header,
    save_checkpoint,
)
from mrchaos.learn.collection import make_collector, make_env, prepare_weights, publish_stage
from mrchaos.learn.config import TrainConfig, config_to_dict, load_config
from mrchaos.learn.curriculum import GLOBAL, LOCAL, CurriculumTransform
from mrchaos.learn.evaluate import evaluate_random
from mrchaos.learn.policy import build_actor_critic, compile_networks
from mrchaos.learn.precision import Autocast, autocast, resolve_precision
from mrchaos.loggers.backends import RunLoggers

__all__ = ["Trainer", "resume_config"]

log = logging.getLogger("mrchaos.learn.ppo")

#: What the PPO loss reads from a batch once advantages are computed.
TRAIN_KEYS = ("observation", "action", "action_log_prob", "advantage", "value_target", "state_value")
LOSS_KEYS = ("loss_objective", "loss_critic", "loss_entropy", "entropy")
CSV_FIELDS = [
    "iteration",
    "frames",
    "episodes",
    "minutes",
    "sps",
    "stage",
    "reward",
    "rela",
    "final",
    *LOSS_KEYS,
    "collect_s",
    "update_s",
    *(f"term_{k}" for k in REWARD_TERMS),
    "lr",
]


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
        self.device = torch.device(cfg.device)
        if self.device.type == "cuda":
            torch.cuda.manual_seed_all(cfg.seed)
        self.stop_requested = False

        n = cfg.env.num_worlds
        if cfg.collector.frames_per_batch % n:
            raise ValueError(
                f"collector.frames_per_batch ({cfg.collector.frames_per_batch}) must be a multiple "
                f"of env.num_worlds ({n})"
            )
        # The curriculum stage: the env reads it, and the collector hands it to its workers.
        self.stage = torch.tensor(GLOBAL if cfg.curriculum.stages == "global" else LOCAL)
        self.env = make_env(cfg, cfg.seed, stage=self.stage)
        self.curriculum: CurriculumTransform = self.env.transform
        base: TangramEnv = self.env.base_env
        self.base = base
        pieces = base.num_pieces if base.free_order else 0  # free order: the policy chooses the piece too
        self.actor_critic = build_actor_critic(cfg.policy, base.grid, base.view, base.action_spec, pieces)
        self.actor_critic = self.actor_critic.to(self.device)
        if cfg.init_from and not resume:
            self._initialise(cfg.init_from)
        prepare_weights(cfg, self.actor_critic)
        if cfg.compile:
            compile_networks(self.actor_critic)
        self.policy = self.actor_critic.get_policy_operator()
        self.value = self.actor_critic.get_value_operator()
        # What the collector stores: the action, its log-probability and the state's value
        # (the value head reads the trunk's output the actor pass already made), not the
        # intermediate features and logits (for the spatial net, gigabytes per batch).
        self.precision = resolve_precision(cfg.precision, self.device)
        self.collect_policy = Autocast(
            TensorDictSequential(
                self.policy,
                self.actor_critic.get_value_head(),
                selected_out_keys=["action", "action_log_prob", "state_value"],
            ),
            self.precision,
        )
        # GAE reads the values :meth:`values` writes: the collector's, shifted along time for
        # the next states, so that the trunk does not run again over the whole batch.
        self.advantage = GAE(gamma=cfg.loss.gamma, lmbda=cfg.loss.lmbda, value_network=None, average_gae=False)
        # The critic gets only its head: the actor's pass has already written the shared
        # trunk's output, so the trunk runs once per minibatch instead of twice.
        self.loss = ClipPPOLoss(
            self.policy,
            self.actor_critic.get_value_head(),
            clip_epsilon=cfg.loss.clip_epsilon,
            entropy_coeff=cfg.loss.entropy_coeff,
            critic_coeff=cfg.loss.critic_coeff,
            normalize_advantage=cfg.loss.normalize_advantage,
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
        self.csv_path = self.run_dir / "metrics.csv"
        if resume and self.csv_path.exists():
            self._truncate_metrics()
        rerun_file = "recording.rrd" if not resume else f"recording.resume{self.iteration}.rrd"
        self.loggers = RunLoggers(
            cfg.logger.backends,
            cfg.name,
            self.run_dir,
            rerun_file=rerun_file,
            online=cfg.logger.online,
            project=cfg.logger.project,
        )
        self.loggers.log_hparams(config_to_dict(cfg))
        # Last: worker processes and Ray actors start here.
        self.collector = make_collector(cfg, self.env, self.collect_policy, self.stage)

    # ------------------------------------------------------------------ parts

    def state(self) -> dict[str, Any]:
        """Everything a resume needs (tensors and builtin containers only)."""
        return {
            **policy_header(self.base, config_to_dict(self.cfg.policy)),
            "config": config_to_dict(self.cfg),
            "model": self.actor_critic.state_dict(),
            "optim": self.optim.state_dict(),
            "curriculum": {
                "stage": int(self.curriculum.stage),
                "switched_at": int(self.curriculum.switched_at),
                **self.curriculum.extra_state(),
            },
            "rng": {
                "torch": torch.get_rng_state(),
                "env": self.base.rng_state(),
                **({"cuda": torch.cuda.get_rng_state_all()} if self.device.type == "cuda" else {}),
            },
            "iteration": self.iteration,
            "frames": self.frames,
            "episodes": self.episodes,
            "minutes": self.minutes,
        }

    def _load_weights(self, path: Path) -> dict[str, Any]:
        """A checkpoint that fits this env, its weights loaded into the actor-critic."""
        return load_weights(self.actor_critic, path, self.base)

    def _restore(self, path: Path) -> None:
        st = self._load_weights(path)
        try:
            self.optim.load_state_dict(st["optim"])
        except (RuntimeError, KeyError, ValueError) as e:
            raise CheckpointError(f"{path}: weights do not fit this policy config ({str(e)[:200]})") from None
        cur = st["curriculum"]
        self.curriculum.stage.fill_(cur["stage"])
        self.curriculum.switched_at.fill_(cur["switched_at"])
        self.curriculum.load_extra_state(cur)
        torch.set_rng_state(st["rng"]["torch"])
        if self.device.type == "cuda" and "cuda" in st["rng"]:
            torch.cuda.set_rng_state_all(st["rng"]["cuda"])
        env_rng = st["rng"]["env"]
        if not isinstance(env_rng, dict):  # checkpoints before the env's rng_state(): two entries
            env_rng = {"torch": env_rng, "numpy": st["rng"]["env_np"]}
        self.base.set_rng_state(env_rng)
        self.iteration, self.frames = st["iteration"], st["frames"]
        self.episodes, self.minutes = st["episodes"], st["minutes"]
        log.info("resumed %s at iteration %d, %d frames, stage %d", path, self.iteration, self.frames, cur["stage"])

    def _initialise(self, spec: str) -> None:
        """Start from another run's weights (a fresh optimiser): PPO on top of a supervised policy."""
        path = checkpoint_path(spec)
        self._load_weights(path)
        log.info("initialised the policy from %s", path)

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
        """Drop rows of iterations after the checkpoint (a killed run redoes them); rewrite an
        older release's header with today's columns."""
        with open(self.csv_path, newline="") as f:
            reader = csv.DictReader(f)
            rows = list(reader)
            header = reader.fieldnames
        keep = [r for r in rows if int(r["iteration"]) <= self.iteration]
        if len(keep) < len(rows) or header != CSV_FIELDS:
            lines = [",".join(CSV_FIELDS)] + [",".join(str(r.get(k) or "") for k in CSV_FIELDS) for r in keep]
            write_atomic(self.csv_path, "\n".join(lines) + "\n")

    def _log(self, row: dict[str, Any], data: TensorDict) -> None:
        new = not self.csv_path.exists()
        with open(self.csv_path, "a", newline="") as f:
            w = csv.DictWriter(f, fieldnames=CSV_FIELDS)
            if new:
                w.writeheader()
            w.writerow({k: row.get(k, "") for k in CSV_FIELDS})
        for k in ("reward", "rela", "final", *LOSS_KEYS, "stage", "sps", "lr", *(f"term_{t}" for t in REWARD_TERMS)):
            self.loggers.log_scalar(k, row.get(k), step=self.iteration)
        rerun = self.loggers.get("rerun")
        every = max(1, self.cfg.logger.image_every)
        if rerun is not None and (self.iteration % every == 1 or every == 1):
            data = data.reshape(-1, data.shape[-1])  # (worlds, time), also for multi-worker batches
            k = min(self.cfg.logger.image_worlds, data.shape[0])
            rerun.log_worlds(
                self.iteration,
                data["observation"][:k, -1].cpu().numpy(),
                data["action"][:k, -1, -3:].cpu().numpy(),  # (x, y, theta): free order's piece comes first
                data["next", "reward"][:k, -1, 0].cpu().numpy(),
                (self.base.grid.xs, self.base.grid.ys),
                self.base.view.extent,
            )

    # ------------------------------------------------------------------ algorithm
    def update(self, data: TensorDict) -> dict[str, float]:
        """PPO on one batch: advantages once, then epochs of minibatches; mean losses."""
        cfg = self.cfg
        with torch.no_grad():
            self.values(data)
            self.advantage(data)
        self.buffer.empty()
        # Only what the loss reads: the next observations alone would double every minibatch's copy.
        # (With free order the policy also reads the pieces left and the action mask.)
        self.buffer.extend(data.select(*dict.fromkeys([*TRAIN_KEYS, *self.policy.in_keys])).reshape(-1))
        sums = dict.fromkeys(LOSS_KEYS, 0.0)
        n_mb = max(1, cfg.collector.frames_per_batch // cfg.loss.minibatch_size)
        for _ in range(cfg.loss.epochs):
            for _ in range(n_mb):
                batch = self.buffer.sample()
                with autocast(self.precision, self.device):
                    out = self.loss(batch)
                total = out["loss_objective"] + out["loss_critic"] + out["loss_entropy"]
                self.optim.zero_grad(set_to_none=True)
                total.backward()
                torch.nn.utils.clip_grad_norm_(self.loss.parameters(), cfg.optim.max_grad_norm)
                self.optim.step()
                for k in sums:
                    sums[k] += float(out[k].detach()) / (cfg.loss.epochs * n_mb)
        return sums

    def values(self, data: TensorDict) -> None:
        """Write ``("next", "state_value")`` for a (worlds, time) batch whose ``state_value`` the collector wrote.

        The next state of a step that did not end its episode is the following step's
        state, whose value is known. Only the batch's last step and truncated episodes
        (whose next state is not the reset one that follows) need the value network; a
        terminated episode's next value is masked out by GAE.
        """
        v = data["state_value"]
        nxt = torch.zeros_like(v)
        nxt[..., :-1, :] = v[..., 1:, :]
        need = data["next", "done"] & ~data["next", "terminated"]
        need[..., -1, :] = True
        need = need[..., 0]
        with autocast(self.precision, self.device):
            nxt[need] = self.value(data["next"][need].select(*self.value.in_keys))["state_value"].float()
        data.set(("next", "state_value"), nxt)

    def curriculum_step(self, reward: float) -> str | None:
        """Switch to stage 2 when stage-1 reward plateaus or the time cap passes; the reason, if it switched.

        The env reads the switched stage at once; :func:`publish_stage` takes it to Ray actors."""
        cap = self.cfg.curriculum.max_minutes
        if int(self.curriculum.stage) != LOCAL:
            return None
        if self.curriculum.update(self.iteration, reward):
            why = "stage-1 reward plateaued"
        elif 0 < cap <= self.minutes and self.curriculum.force_switch(self.iteration):
            why = f"time cap of {cap:g} min"
        else:
            return None
        return why

    @staticmethod
    def batch_metrics(data: TensorDict) -> dict[str, float | int]:
        """What a collected batch says: episodes ended (``ended``), mean reward, Rela of its steps, Final of its
        ended episodes, and the mean of every reward term over the steps that placed a piece."""
        done = data["next", "done"][..., 0]
        acted = data["next", "info", "piece"][..., 0] >= 0
        step_cov = data["next", "info", "step_coverage"][..., 0][acted]
        finals = data["next", "info", "final"][..., 0][done]
        terms = data["next", "info", "reward_terms"]
        return {
            "ended": int(done.sum()),
            "reward": float(data["next", "reward"].mean()),
            "rela": float(step_cov.mean()) if len(step_cov) else float("nan"),
            "final": float(finals.mean()) if len(finals) else float("nan"),
            **{
                f"term_{k}": float(terms[k][..., 0][acted].mean()) if acted.any() else float("nan")
                for k in terms.keys()
            },
        }

    # ------------------------------------------------------------------ loop
    def run(self) -> dict[str, Any]:
        """Collect, update, step the curriculum, log and checkpoint until a stop rule fires."""
        cfg = self.cfg
        write_atomic(self.run_dir / "config.yaml", yaml.safe_dump(config_to_dict(cfg), sort_keys=False))
        old_handlers = {s: signal.signal(s, self._request_stop) for s in (signal.SIGINT, signal.SIGTERM)}
        bar = self._progress_bar()
        started = time.perf_counter() - self.minutes * 60
        t_collect = time.perf_counter()
        try:
            for data in self.collector:
                data = data.to(self.device)
                collect_s = time.perf_counter() - t_collect
                t_update = time.perf_counter()
                self.iteration += 1
                self.frames += data.numel()
                seen = self.batch_metrics(data)
                self.episodes += int(seen["ended"])
                stage = int(self.curriculum.stage)

                lr = cfg.optim.learning_rate(self.progress)
                for group in self.optim.param_groups:
                    group["lr"] = lr
                losses = self.update(data)

                self.minutes = (time.perf_counter() - started) / 60
                why = self.curriculum_step(seen["reward"])
                if why is not None:
                    self._event(f"curriculum: stage 1 -> 2 at iteration {self.iteration} ({self.frames} frames; {why})")
                    publish_stage(self.collector, self.stage)
                # New weights to every worker before the next batch.
                self.collector.update_policy_weights_()
                update_s = time.perf_counter() - t_update
                row = {
                    "iteration": self.iteration,
                    "frames": self.frames,
                    "episodes": self.episodes,
                    "minutes": round(self.minutes, 3),
                    "sps": data.numel() / (collect_s + update_s),
                    "stage": stage,
                    "collect_s": round(collect_s, 3),
                    "update_s": round(update_s, 3),
                    **seen,
                    **losses,
                    "lr": lr,
                }
                self._log(row, data)
                if bar is not None:
                    bar.update(data.numel())
                    bar.set_postfix(
                        sps=f"{row['sps']:.0f}",
                        reward=f"{row['reward']:.3f}",
                        rela=f"{row['rela']:.3f}",
                        stage=stage,
                        refresh=False,
                    )
                if self.iteration % max(1, cfg.checkpoint.every) == 0:
                    self.save()
                if self._should_stop():
                    break
                t_collect = time.perf_counter()
        finally:
            for s, h in old_handlers.items():
                signal.signal(s, h)
            if bar is not None:
                bar.close()
            self.collector.shutdown()
            self.save()
            self.loggers.close()
        return {"iteration": self.iteration, "frames": self.frames, "stopped": self.stop_requested}

    @property
    def progress(self) -> float:
        """The used fraction of the run's budget: the larger of its frames' and its minutes' (0 without one)."""
        c = self.cfg.collector
        return max(
            self.frames / c.total_frames if c.total_frames > 0 else 0.0,
            self.minutes / c.max_minutes if c.max_minutes > 0 else 0.0,
        )

    def _should_stop(self) -> bool:
        over_frames = 0 < self.cfg.collector.total_frames <= self.frames
        over_time = 0 < self.cfg.collector.max_minutes <= self.minutes
        return over_frames or over_time or self.stop_requested

    def _progress_bar(self):
        if not self.cfg.logger.progress:
            return None
        from tqdm import tqdm

        total = self.cfg.collector.total_frames if self.cfg.collector.total_frames > 0 else None
        # The run's name, a recipe's stage inside a staged run.
        return tqdm(total=total, initial=self.frames, unit="f", dynamic_ncols=True, desc=self.cfg.name)

    def _event(self, msg: str) -> None:
        log.info(msg)
        self.loggers.log_text("events", msg, step=self.iteration)

    def finish(self, n_eval: int = 200) -> dict[str, float]:
        """Greedy evaluation on Random objects, written to ``eval.json``."""
        res = evaluate_random(self.policy, self.cfg.env_config(), n=n_eval)
        write_atomic(self.run_dir / "eval.json", json.dumps(res, indent=1) + "\n")
        return res


def resume_config(run_dir: Path) -> TrainConfig:
    """The config a run was started with (its ``config.yaml``)."""
    path = Path(run_dir) / "config.yaml"
    if not path.exists():
        raise FileNotFoundError(f"{run_dir}: not a run directory (no config.yaml)")
    return load_config(path)
