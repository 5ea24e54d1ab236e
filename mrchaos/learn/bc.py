"""Supervised learning from the simulator's answers: the paper's BC baseline, BC on chaos, dense targets, DAgger.

A demonstration is a target assembled in the simulator piece by piece: every state along
the way (silhouette plus the pieces already in place) with a label. The targets are
human figures rotated and shifted (``bc.source: figures``, the paper's baseline) or
chaos objects (``source: chaos``, the objects RL trains on). The label is the oracle's
grid action (``bc.targets: oracle``, negative log-likelihood) or, beyond the paper, the
counterfactual coverage of all 20,808 actions (``targets: dense``, a cross-entropy against
softmax(coverage / temperature), actions that land on placed pieces masked), which
grades every action where the oracle names one. DAgger rounds (``bc.dagger_rounds``) let
the policy assemble new chaos objects itself and label the states it reaches, so that
its own compounding errors are learnt from. The network is the same actor as PPO's.
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
from mrchaos.figures.pieces import get_piece_set
from mrchaos.learn.checkpoint import policy_header, save_checkpoint
from mrchaos.learn.config import TrainConfig, config_to_dict
from mrchaos.learn.evaluate import evaluate, evaluate_random, policy_actor
from mrchaos.learn.policy import build_actor_critic
from mrchaos.learn.precision import autocast
from mrchaos.tasks.chaos import generate

__all__ = ["augment", "demonstrations", "supervised_loss", "train_bc"]

log = logging.getLogger("mrchaos.learn.bc")


def augment(figures: list[Figure], rotations: int, shifts: int, max_shift: float, rng: np.random.Generator,
            bound: float) -> tuple[np.ndarray, np.ndarray]:
    """(M, P, 3) target poses and (M, P) bool faces (turned over): each figure rotated about its
    centre and shifted, every vertex kept within ``bound`` metres of the centre (inside the view)."""
    out, faces = [], []
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
                    faces.append(f.mirrored)
    return np.stack(out), np.stack(faces)


#: Dense labels are stored as uint8: coverage * 254, and 255 where physics decides (masked).
_MASKED = 255


def _dense_label(env: TangramEnv, overlap_limit: float) -> torch.Tensor:
    """(N, T, Y, X) uint8 counterfactual coverage of every action, 255 where the footprint overlaps."""
    cov, overlap = env.counterfactual()
    q = (cov * 254).round().to(torch.uint8)
    q[overlap > overlap_limit] = _MASKED
    return q


def demonstrations(env: TangramEnv, targets: np.ndarray, actor=None, dense: bool = False,
                   overlap_limit: float = 0.02, mirrored: np.ndarray | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Observations (M*P, 2, H, W) uint8 along each assembly and their labels.

    ``mirrored`` (M, P) bool marks target pieces that lie turned over (the env needs the flip).

    The assemblies are the oracle's, or ``actor``'s (DAgger: the states a policy reaches);
    the labels are the oracle's grid actions (M*P, 3), or with ``dense`` the counterfactual
    coverage of every grid action (M*P, T, Y, X) uint8 (see :func:`_dense_label`).
    """
    obs, labels = [], []

    def act(e: TangramEnv, td: TensorDict) -> torch.Tensor:
        # Label the state before acting on it; padded worlds of a last chunk are labelled too
        # (they repeat a real target) and are dropped below with the rest of the padding.
        obs.append(td["observation"].clone())
        labels.append(_dense_label(e, overlap_limit) if dense else oracle_actions(e))
        return oracle_actions(e) if actor is None else actor(e, td)

    evaluate(env, targets, act, mirrored=mirrored)
    nw, n, p = env.batch_size[0], len(targets), env.num_pieces
    keep = [min(nw, n - start) for start in range(0, n, nw) for _ in range(p)]
    return (torch.cat([o[:k] for o, k in zip(obs, keep)]), torch.cat([lb[:k] for lb, k in zip(labels, keep)]))


def _targets(cfg: TrainConfig, rng: np.random.Generator, n_chaos: int, seed: int) -> tuple[np.ndarray, np.ndarray, str]:
    """Target poses to demonstrate, their faces (M, P) bool (turned over) and a description:
    augmented figures, or chaos objects."""
    flip = cfg.env.grid.flip
    if cfg.bc.source == "chaos":
        cfg.task.given_targets().check_flip(flip)  # before the objects are generated, not after
        poses, _, mirrored = generate(get_piece_set(cfg.env.piece_set), n_chaos, np.random.default_rng(seed),
                                      cfg.task.chaos, cfg.env.view)
        return poses, mirrored, f"{n_chaos} chaos objects (seed {seed}, {int(mirrored.any(1).sum())} with a piece turned over)"
    figs: list[Figure] = []
    for src in cfg.bc.figure_sets:
        figs += builtin_figures() if src == "builtin" else load_figures(src).figures
    if not flip:  # without the flip, a figure that needs a turned-over piece cannot be assembled
        figs = [f for f in figs if not f.has_mirrored]
    poses, mirrored = augment(figs, cfg.bc.rotations, cfg.bc.shifts, cfg.bc.max_shift, rng,
                              cfg.task.chaos.bound(cfg.env.view))
    return poses, mirrored, f"{len(figs)} figures ({len(poses)} augmented)"


def supervised_loss(policy, obs: torch.Tensor, labels: torch.Tensor, dense: bool, temperature: float) -> torch.Tensor:
    """Negative log-likelihood of oracle actions, or the cross-entropy against softmax(coverage / T)."""
    dist = policy.get_dist(TensorDict(observation=obs, batch_size=[len(obs)]))
    if not dense:
        return -dist.log_prob(labels).mean()
    q = labels.flatten(1)
    logits = torch.where(q == _MASKED, -torch.inf, q.float() / 254 / temperature)
    target = torch.softmax(logits, -1)
    return -(target * dist.logits).sum(-1).mean()


def train_bc(cfg: TrainConfig, run_dir: Path) -> dict:
    """Train the configured network by supervision (oracle actions or dense targets, optionally
    with DAgger rounds); writes a checkpoint like PPO's."""
    run_dir = Path(run_dir)
    (run_dir / "checkpoints").mkdir(parents=True, exist_ok=True)
    write_atomic(run_dir / "config.yaml", yaml.safe_dump(config_to_dict(cfg), sort_keys=False))
    torch.set_num_threads(cfg.threads)
    torch.manual_seed(cfg.seed)
    bc = cfg.bc
    dense = bc.targets == "dense"
    rng = np.random.default_rng(cfg.seed)
    targets, faces, what = _targets(cfg, rng, bc.objects, bc.seed)
    env = TangramEnv(dataclasses.replace(cfg.env_config(), num_worlds=min(128, len(targets)),
                                         task=cfg.task.given_targets()), seed=cfg.seed)
    t0 = time.perf_counter()
    obs, labels = demonstrations(env, targets, dense=dense, overlap_limit=bc.overlap_limit, mirrored=faces)
    log.info("%d demonstration steps from %s in %.0f s", len(obs), what, time.perf_counter() - t0)
    device = torch.device(cfg.device)
    ac = build_actor_critic(cfg.policy, env.grid, env.view, env.action_spec).to(device)
    policy = ac.get_policy_operator()
    opt = torch.optim.Adam(ac.parameters(), lr=cfg.optim.lr, weight_decay=cfg.optim.weight_decay)
    rows: list[dict] = []
    # The budget that ``optim.lr_final`` anneals over is every planned epoch, DAgger rounds included.
    planned = bc.epochs + bc.dagger_rounds * bc.dagger_epochs

    def fit(epochs: int, round_: int) -> None:
        n = len(obs)
        for _ in range(epochs):
            perm = torch.randperm(n)
            total, count = 0.0, 0
            for i in range(0, n, bc.minibatch_size):
                idx = perm[i : i + bc.minibatch_size]
                for group in opt.param_groups:
                    group["lr"] = cfg.optim.learning_rate((len(rows) + i / n) / planned)
                # The labelled data stays on the CPU (it can be large); minibatches go to the device.
                with autocast(cfg.precision, device):
                    loss = supervised_loss(policy, obs[idx].to(device), labels[idx].to(device), dense,
                                           bc.temperature)
                opt.zero_grad(set_to_none=True)
                loss.backward()
                torch.nn.utils.clip_grad_norm_(ac.parameters(), cfg.optim.max_grad_norm)
                opt.step()
                total += loss.item() * len(idx)
                count += len(idx)
            rows.append({"epoch": len(rows) + 1, "round": round_, "samples": n, "loss": total / count,
                         "lr": opt.param_groups[0]["lr"], "minutes": (time.perf_counter() - t0) / 60})
            log.info("bc epoch %d (round %d, %d samples): loss %.4f", len(rows), round_, n, total / count)

    fit(bc.epochs, 0)
    greedy = policy_actor(policy)
    for r in range(1, bc.dagger_rounds + 1):
        new, new_faces, what_r = _targets(cfg, rng, bc.dagger_objects, bc.seed + r)
        o, lb = demonstrations(env, new, actor=greedy, dense=dense, overlap_limit=bc.overlap_limit,
                               mirrored=new_faces)
        obs, labels = torch.cat([obs, o]), torch.cat([labels, lb])
        log.info("DAgger round %d: %d states of the policy's own assemblies of %s", r, len(o), what_r)
        fit(bc.dagger_epochs, r)
    state = {
        **policy_header(env, config_to_dict(cfg.policy)), "config": config_to_dict(cfg), "model": ac.state_dict(),
        "curriculum": {"stage": 0, "switched_at": -1}, "iteration": len(rows), "frames": len(obs),
        "episodes": len(targets) + bc.dagger_rounds * bc.dagger_objects, "minutes": (time.perf_counter() - t0) / 60,
    }
    save_checkpoint(run_dir / "checkpoints" / "last.pt", state)
    fields = ["epoch", "round", "samples", "loss", "lr", "minutes"]
    write_atomic(run_dir / "metrics.csv", ",".join(fields) + "\n"
                 + "".join(",".join(f"{r[k]:.6f}" if isinstance(r[k], float) else str(r[k]) for k in fields) + "\n"
                           for r in rows))
    ev = evaluate_random(policy, cfg.env_config(), n=100)
    write_atomic(run_dir / "eval.json", json.dumps(ev, indent=1) + "\n")
    return {"samples": len(obs), "what": what, "loss": rows[-1]["loss"] if rows else float("nan"), **ev}
