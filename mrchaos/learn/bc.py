"""Behaviour cloning, the paper's baseline: supervised imitation of disassembled human figures.

A demonstration is a human figure taken apart in the simulator and put back
together piece by piece: every state along the way (silhouette plus the pieces
already in place) paired with the grid action that puts the next piece on its
target. Figures are rotated by multiples of 45 degrees and shifted to multiply
the data. The network is the same actor as PPO's; the loss is the negative
log-likelihood of the demonstrated action.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import time
from pathlib import Path

import numpy as np
import torch
import yaml
from tensordict import TensorDict

from mrchaos.core.atomic import write_atomic
from mrchaos.core.geometry import rigid_transform
from mrchaos.env.oracle import oracle_actions
from mrchaos.env.tangram import TangramEnv
from mrchaos.figures.figure import Figure
from mrchaos.figures.formats import load_figures
from mrchaos.figures.library import builtin_figures
from mrchaos.learn.checkpoint import policy_header, save_checkpoint
from mrchaos.learn.config import TrainConfig, config_to_dict
from mrchaos.learn.evaluate import evaluate, evaluate_random
from mrchaos.learn.policy import build_actor_critic

__all__ = ["augment", "demonstrations", "train_bc"]

log = logging.getLogger("mrchaos.learn.bc")


def augment(figures: list[Figure], rotations: int, shifts: int, max_shift: float, rng: np.random.Generator,
            bound: float) -> np.ndarray:
    """(M, P, 3) target poses: each figure rotated about its centre and shifted, every vertex kept
    within ``bound`` metres of the centre (inside the view)."""
    out = []
    for f in figures:
        for k in range(rotations):
            a = 2 * math.pi * k / rotations
            c, s = math.cos(a), math.sin(a)
            rot = f.poses.copy()
            rot[:, 0], rot[:, 1] = c * f.poses[:, 0] - s * f.poses[:, 1], s * f.poses[:, 0] + c * f.poses[:, 1]
            rot[:, 2] = (rot[:, 2] + a + math.pi) % (2 * math.pi) - math.pi
            outline = f.piece_set.padded_outlines(f.mirrored)
            for j in range(shifts + 1):
                d = np.zeros(2) if j == 0 else rng.uniform(-max_shift, max_shift, 2)
                cand = rot.copy()
                cand[:, :2] += d
                if np.abs(rigid_transform(outline, cand)).max() <= bound:
                    out.append(cand)
    return np.stack(out)


def demonstrations(env: TangramEnv, targets: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """Observations (M*P, 2, H, W) uint8 and oracle grid actions (M*P, 3) along each assembly."""
    res = evaluate(env, targets, lambda e, td: oracle_actions(e), record_steps=True)
    obs = torch.cat([torch.from_numpy(s["observation"]) for s in res.steps])
    acts = torch.cat([torch.from_numpy(s["action"]) for s in res.steps])
    return obs, acts


def train_bc(cfg: TrainConfig, run_dir: Path) -> dict:
    """Train the configured network by behaviour cloning; writes a checkpoint like PPO's."""
    run_dir = Path(run_dir)
    (run_dir / "checkpoints").mkdir(parents=True, exist_ok=True)
    write_atomic(run_dir / "config.yaml", yaml.safe_dump(config_to_dict(cfg), sort_keys=False))
    torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    figs: list[Figure] = []
    for src in cfg.bc.figure_sets:
        figs += builtin_figures() if src == "builtin" else load_figures(src).figures
    figs = [f for f in figs if not f.has_mirrored]
    targets = augment(figs, cfg.bc.rotations, cfg.bc.shifts, cfg.bc.max_shift, rng, cfg.task.chaos.bound(cfg.env.view))
    env = TangramEnv(dataclasses.replace(cfg.env_config(), num_worlds=min(128, len(targets))), seed=cfg.seed)
    t0 = time.perf_counter()
    obs, acts = demonstrations(env, targets)
    log.info("%d demonstrations from %d figures (%d augmented) in %.0f s", len(obs), len(figs), len(targets),
             time.perf_counter() - t0)
    ac = build_actor_critic(cfg.policy, env.grid, env.view, env.action_spec)
    policy = ac.get_policy_operator()
    opt = torch.optim.Adam(ac.parameters(), lr=cfg.optim.lr)
    n = len(obs)
    rows = []
    for epoch in range(cfg.bc.epochs):
        perm = torch.randperm(n)
        total, count = 0.0, 0
        for i in range(0, n, cfg.bc.minibatch_size):
            idx = perm[i : i + cfg.bc.minibatch_size]
            td = TensorDict(observation=obs[idx], batch_size=[len(idx)])
            dist = policy.get_dist(td)
            loss = -dist.log_prob(acts[idx]).mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(ac.parameters(), cfg.optim.max_grad_norm)
            opt.step()
            total += loss.item() * len(idx)
            count += len(idx)
        rows.append({"epoch": epoch + 1, "nll": total / count})
        log.info("bc epoch %d: nll %.3f", epoch + 1, total / count)
    state = {
        **policy_header(env, config_to_dict(cfg.policy)), "config": config_to_dict(cfg), "model": ac.state_dict(),
        "curriculum": {"stage": 0, "switched_at": -1}, "iteration": cfg.bc.epochs, "frames": n,
        "episodes": len(targets), "minutes": (time.perf_counter() - t0) / 60,
    }
    save_checkpoint(run_dir / "checkpoints" / "last.pt", state)
    write_atomic(run_dir / "metrics.csv", "epoch,nll\n" + "".join(f"{r['epoch']},{r['nll']:.6f}\n" for r in rows))
    ev = evaluate_random(policy, cfg.env_config(), n=100)
    write_atomic(run_dir / "eval.json", json.dumps(ev, indent=1) + "\n")
    return {"samples": n, "figures": len(figs), "nll": rows[-1]["nll"] if rows else float("nan"), **ev}
