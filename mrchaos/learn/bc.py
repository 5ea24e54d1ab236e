"""Supervised learning from the simulator's answers: the paper's BC baseline, BC on chaos, dense
targets, DAgger and expert iteration.

A demonstration is a target assembled in the simulator piece by piece: every state along
the way (silhouette plus the pieces already in place) with a label. The targets are
human figures rotated and shifted (``bc.source: figures``, the paper's baseline) or
chaos objects (``source: chaos``, the objects RL trains on). The label is the oracle's
grid action (``bc.targets: oracle``, negative log-likelihood) or, beyond the paper, the
counterfactual coverage of all 20,808 actions (``targets: dense``, a cross-entropy against
softmax(coverage / temperature), actions that land on placed pieces masked), which
grades every action where the oracle names one. DAgger rounds (``bc.dagger_rounds``) let
the policy assemble new chaos objects itself and label the states it reaches, so that
its own compounding errors are learnt from. Expert-iteration rounds (``exit.rounds``, Anthony
et al. 2017) let the lookahead planner around the policy (:mod:`mrchaos.learn.planner`, which
reads no solution) assemble new chaos objects, and teach the policy the planner's ranking of
its own top-k candidates at every state (:func:`ranking_loss`) beside the dense targets of the
same states; the better policy makes the better planner for the next round. The network is the
same actor as PPO's. Every epoch leaves a checkpoint, so a run resumes where it stopped.

With free order (``env.order: free``) the dense label grades the placements of every piece a state
allows, kept as its best actions and the rest's mass (:func:`free_label`,
:func:`free_supervised_loss`); demonstrations place the pieces in random orders, and the planner's
candidates in expert-iteration rounds name the piece with the placement.
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
from tensordict import TensorDict

from mrchaos.core.atomic import write_atomic
from mrchaos.core.geometry import rigid_transform
from mrchaos.env.oracle import oracle_actions, random_pieces
from mrchaos.env.tangram import TangramEnv, free_order_inputs
from mrchaos.figures.figure import Figure
from mrchaos.figures.formats import load_figures
from mrchaos.figures.library import builtin_figures
from mrchaos.figures.pieces import get_piece_set
from mrchaos.learn.checkpoint import CheckpointError, checkpoint_path, load_weights, policy_header, save_checkpoint
from mrchaos.learn.config import TrainConfig, config_to_dict, start_run
from mrchaos.learn.evaluate import evaluate, evaluate_random, policy_actor
from mrchaos.learn.planner import Lookahead
from mrchaos.learn.policy import MASKED_LOGIT, GridCategorical, PieceGridCategorical, build_actor_critic
from mrchaos.learn.precision import autocast
from mrchaos.learn.rerank import listwise_loss
from mrchaos.tasks.chaos import generate

__all__ = [
    "augment",
    "demonstrations",
    "supervised_loss",
    "dense_target_logits",
    "ranking_loss",
    "SupervisedRun",
    "train_bc",
    "METRIC_FIELDS",
]

log = logging.getLogger("mrchaos.learn.bc")


def augment(
    figures: list[Figure], rotations: int, shifts: int, max_shift: float, rng: np.random.Generator, bound: float
) -> tuple[np.ndarray, np.ndarray]:
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


def _dense_label(
    env: TangramEnv, overlap_limit: float, rows: np.ndarray | None = None, piece: np.ndarray | None = None
) -> torch.Tensor:
    """(N, T, Y, X) uint8 counterfactual coverage of every action (of worlds ``rows``, default
    all; of ``piece`` (N,), which free order needs), 255 where the footprint overlaps."""
    cov, overlap = env.counterfactual(rows, piece)
    q = (cov * 254).round().to(torch.uint8)
    q[overlap > overlap_limit] = _MASKED
    return q


def _set_order_label(
    env: TangramEnv, dense: bool, overlap_limit: float, rows: np.ndarray | None = None
) -> dict[str, torch.Tensor]:
    """The label of worlds ``rows`` (default all) in the set's order: ``label``, the oracle's grid
    action (N, 3 or 4) or with ``dense`` the counterfactual coverage (:func:`_dense_label`); dense
    on a refined grid also ``fine_label`` (N, 4), the oracle's refined action: the dense targets
    grade the coarse cells, and the offset is learnt at the oracle's own cell."""
    if dense and not env.grid.refined:
        return {"label": _dense_label(env, overlap_limit, rows)}
    oracle = oracle_actions(env) if rows is None else oracle_actions(env)[rows]
    if not dense:
        return {"label": oracle}
    return {"label": _dense_label(env, overlap_limit, rows), "fine_label": oracle}


#: Free-order labels keep each state's best actions over all its choosable pieces (a full label
#: would be P times the fixed order's: 145 kB a state for the tangram set); the softmax(coverage /
#: T) target puts 98.9 % of its mass on the best 256 on average (measured on conf/flip_exit.yaml's
#: dense labels), and the rest's mass is kept as one number (:func:`free_label`).
FREE_LABEL_TOP = 256

#: The extra keys of a free-order shard: the label's coverage of its kept actions, the log of the
#: target mass of the actions not kept, and what the policy reads besides the image.
FREE_SHARD_KEYS = ("label_coverage", "label_rest", "remaining", "choosable")


def free_label(
    env: TangramEnv, overlap_limit: float, temperature: float, rows: np.ndarray | None = None, top: int = FREE_LABEL_TOP
) -> dict[str, torch.Tensor]:
    """The dense label of every world (or of worlds ``rows``) with free order, over the placements of
    every piece it may choose (:meth:`TangramEnv.choosable`): ``label`` (R, top) int32 flat indices
    (piece, theta, y, x) of the best actions by counterfactual coverage (-1 pads; footprints on
    placed pieces are left out, as in :func:`_dense_label`), ``label_coverage`` (R, top) uint8 their
    coverage * 254, and ``label_rest`` (R,) float32 the log of the summed exp(coverage /
    ``temperature``) of the allowed actions not kept (-inf when none)."""
    n = env.batch_size[0]
    r = np.arange(n) if rows is None else np.asarray(rows)
    ok = env.choosable()[r]
    g = env.grid
    per = g.norient * g.ny * g.nx
    q = torch.full((len(r), env.num_pieces * per), -1, dtype=torch.int16)
    for p in np.flatnonzero(ok.any(0)):
        sel = np.flatnonzero(ok[:, p])
        c = _dense_label(env, overlap_limit, r[sel], np.full(n, p)).flatten(1).to(torch.int16)
        q[torch.as_tensor(sel), p * per : (p + 1) * per] = torch.where(c == _MASKED, -1, c)
    val, idx = q.topk(top, -1)
    allowed = q >= 0
    logits = torch.where(allowed, q.float() / 254 / temperature, -torch.inf)
    logits.scatter_(1, idx, -torch.inf)  # what is kept leaves the rest
    return {
        "label": torch.where(val >= 0, idx, -1).to(torch.int32),
        "label_coverage": val.clamp_min(0).to(torch.uint8),
        "label_rest": torch.logsumexp(logits, -1),
    }


def demonstrations(
    env: TangramEnv,
    targets: np.ndarray,
    actor=None,
    dense: bool = False,
    overlap_limit: float = 0.02,
    mirrored: np.ndarray | None = None,
    temperature: float = 0.01,
    generator: torch.Generator | None = None,
) -> dict[str, torch.Tensor]:
    """The states along each assembly and their labels: ``observation`` (M*P, 2, H, W) uint8 and
    ``label``.

    ``mirrored`` (M, P) bool marks target pieces that lie turned over (the env needs the flip).

    The assemblies are the oracle's, or ``actor``'s (DAgger: the states a policy reaches);
    the labels are the oracle's grid actions (M*P, 3), or with ``dense`` the counterfactual
    coverage of every grid action (M*P, T, Y, X) uint8 (see :func:`_dense_label`), and on a refined
    grid the oracle's refined action too (``fine_label`` (M*P, 4): its offset is learnt at its
    cell). With free
    order (dense only) the label is :func:`free_label`'s (``temperature`` is its target's), the
    oracle places its pieces in an order drawn with ``generator``, and the states also hold
    ``remaining`` and ``choosable`` (M*P, P) bool.
    """
    if env.free_order and not dense:
        raise ValueError("with env.order: free, supervision needs dense targets (bc.targets: dense)")
    parts: dict[str, list[torch.Tensor]] = {}
    order = generator if generator is not None else torch.Generator().manual_seed(0)

    def add(key: str, value: torch.Tensor) -> None:
        parts.setdefault(key, []).append(value)

    def act(e: TangramEnv, td: TensorDict) -> torch.Tensor:
        # Label the state before acting on it; padded worlds of a last chunk are labelled too
        # (they repeat a real target) and are dropped below with the rest of the padding.
        add("observation", td["observation"].clone())
        if e.free_order:
            for key, value in free_label(e, overlap_limit, temperature).items():
                add(key, value)
            add("remaining", td["remaining"].clone())
            add("choosable", torch.as_tensor(e.choosable()))
            if actor is None:
                return oracle_actions(e, random_pieces(e, order))
        else:
            for key, value in _set_order_label(e, dense, overlap_limit).items():
                add(key, value)
        return oracle_actions(e) if actor is None else actor(e, td)

    evaluate(env, targets, act, mirrored=mirrored)
    nw, n, p = env.batch_size[0], len(targets), env.num_pieces
    keep = [min(nw, n - start) for start in range(0, n, nw) for _ in range(p)]
    return {key: torch.cat([v[:k] for v, k in zip(vs, keep, strict=True)]) for key, vs in parts.items()}


def _targets(cfg: TrainConfig, rng: np.random.Generator, n_chaos: int, seed: int) -> tuple[np.ndarray, np.ndarray, str]:
    """Target poses to demonstrate, their faces (M, P) bool (turned over) and a description:
    augmented figures, or chaos objects."""
    flip = cfg.env.grid.flip
    if cfg.bc.source == "chaos":
        cfg.task.given_targets().check_flip(flip)  # before the objects are generated, not after
        poses, _, mirrored = generate(
            get_piece_set(cfg.env.piece_set), n_chaos, np.random.default_rng(seed), cfg.task.chaos, cfg.env.view
        )
        turned = int(mirrored.any(1).sum())
        return poses, mirrored, f"{n_chaos} chaos objects (seed {seed}, {turned} with a piece turned over)"
    figs: list[Figure] = []
    for src in cfg.bc.figure_sets:
        figs += builtin_figures() if src == "builtin" else load_figures(src).figures
    if not flip:  # without the flip, a figure that needs a turned-over piece cannot be assembled
        figs = [f for f in figs if not f.has_mirrored]
    poses, mirrored = augment(
        figs, cfg.bc.rotations, cfg.bc.shifts, cfg.bc.max_shift, rng, cfg.task.chaos.bound(cfg.env.view)
    )
    return poses, mirrored, f"{len(figs)} figures ({len(poses)} augmented)"


def supervised_loss(dist, labels: torch.Tensor, dense: bool, temperature: float) -> torch.Tensor:
    """Per-sample negative log-likelihood of oracle actions, or cross-entropy against softmax(coverage / T)."""
    if not dense:
        return -dist.log_prob(labels)
    target = torch.softmax(dense_target_logits(labels, temperature), -1)
    return -(target * dist.logits).sum(-1)


def dense_target_logits(labels: torch.Tensor, temperature: float) -> torch.Tensor:
    """(N, A) logits of the dense targets softmax(coverage / T) of uint8 labels (N, T, Y, X) (see
    :func:`_dense_label`); -inf where physics decides (masked)."""
    q = labels.flatten(1)
    return torch.where(q == _MASKED, -torch.inf, q.float() / 254 / temperature)


def free_supervised_loss(
    dist: PieceGridCategorical, label: torch.Tensor, coverage: torch.Tensor, rest: torch.Tensor, temperature: float
) -> torch.Tensor:
    """Per-sample cross-entropy against a free-order label (:func:`free_label`): softmax(coverage / T)
    over the kept actions, and the rest's mass spread evenly over the other actions of the pieces
    the state allows (those whose logits the policy has not masked)."""
    scores = dist.scores
    lse = torch.logsumexp(scores, -1)
    valid = label >= 0
    kept = torch.where(valid, scores.gather(-1, label.long().clamp_min(0)) - lse[:, None], 0.0)
    target = torch.softmax(
        torch.cat([torch.where(valid, coverage.float() / 254 / temperature, -torch.inf), rest[:, None].float()], -1),
        -1,
    )
    # Sums per piece: a masked piece's channels all hold MASKED_LOGIT, and drop out whole (one pass
    # over the scores instead of a masked copy of them).
    per_piece = scores.reshape(len(scores), dist.pieces, -1)
    allowed = per_piece[:, :, 0] > MASKED_LOGIT / 2
    total = torch.where(allowed, per_piece.sum(-1), 0.0).sum(-1) - allowed.sum(-1) * per_piece.shape[-1] * lse
    others = (allowed.sum(-1) * per_piece.shape[-1] - valid.sum(-1)).clamp_min(1)
    mean_rest = (total - kept.sum(-1)) / others
    return -((target[:, :-1] * kept).sum(-1) + target[:, -1] * mean_rest)


def ranking_loss(
    dist: GridCategorical, candidates: torch.Tensor, iou: torch.Tensor, temperature: float
) -> torch.Tensor:
    """Per-sample listwise loss: the cross-entropy between softmax(IoU / T) over a state's planner
    candidates (B, k, 3) and the softmax of the policy's mode scores at the same candidates, the
    scores whose argmax is the deterministic action (windowed under a mode window)."""
    return listwise_loss(dist.scores_at(candidates), iou, temperature)


#: The pieces of a labelled shard; ``candidates`` and ``iou`` hold the planner's judgement (NaN IoU
#: where a state has none: demonstrations and DAgger).
SHARD_KEYS = ("observation", "label", "candidates", "iou")


class SupervisedRun:
    """A supervised run as rounds of labelled data, each followed by passes over all data so far:
    round 0 the demonstrations, then DAgger rounds (the policy's own assemblies, labelled by the
    oracle or dense targets), then expert-iteration rounds (the planner's assemblies, labelled with
    its ranking of the policy's candidates and the dense or oracle targets of the same states).

    Crash safety: each round's data is written to ``data/round_R.pt`` before it is learnt from,
    and after every epoch the checkpoint ``checkpoints/last.pt`` (weights, optimiser, RNG, the
    round and epoch) and ``metrics.csv`` are rewritten atomically, so ``resume=True`` continues
    after the last finished epoch as if the run had not stopped. The policy at the end of round
    R is kept as ``checkpoints/roundR.pt``.
    """

    def __init__(self, cfg: TrainConfig, run_dir: Path, resume: bool = False) -> None:
        self.cfg, self.run_dir = cfg, Path(run_dir)
        self.ckpt = start_run(cfg, self.run_dir, resume)
        self.rng = np.random.default_rng(cfg.seed)
        self.dense = cfg.bc.targets == "dense"
        self.device = torch.device(cfg.device)
        bc, ex = cfg.bc, cfg.exit
        #: (kind, epochs) of every round, in order.
        self.plan = (
            [("demo", bc.epochs)]
            + [("dagger", bc.dagger_epochs)] * bc.dagger_rounds
            + [("exit", ex.epochs)] * ex.rounds
        )
        if ex.rounds and cfg.env.num_worlds < ex.k:
            raise ValueError(f"exit.k={ex.k} candidates need env.num_worlds >= {ex.k}, got {cfg.env.num_worlds}")
        self.free = cfg.env.order == "free"  # dense targets only (TrainConfig checks)
        #: What a shard holds: with free order also the sparse label's parts and the policy's inputs;
        #: on a refined grid with dense labels also the oracle's refined action (the offset's loss).
        fine = ("fine_label",) if self.dense and cfg.env.grid.refined else ()
        self.keys = SHARD_KEYS + (FREE_SHARD_KEYS if self.free else ()) + fine
        self.env = TangramEnv(dataclasses.replace(cfg.env_config(), task=cfg.task.given_targets()), seed=cfg.seed)
        pieces = self.env.num_pieces if self.free else 0  # free order: the policy chooses the piece too
        self.ac = build_actor_critic(cfg.policy, self.env.grid, self.env.view, self.env.action_spec, pieces)
        self.ac = self.ac.to(self.device)
        # The oracle's piece order in free-order demonstrations.
        self.order_generator = torch.Generator().manual_seed(cfg.seed)
        self.policy = self.ac.get_policy_operator()
        self.opt = torch.optim.Adam(self.ac.parameters(), lr=cfg.optim.lr, weight_decay=cfg.optim.weight_decay)
        self.rows: list[dict] = []
        self.round, self.epoch, self.episodes, self.minutes = 0, 0, 0, 0.0
        self.shards: list[dict[str, torch.Tensor]] = []
        #: The planner's figures of the round being learnt (logged with its first epoch).
        self.round_metrics: dict[str, float] = {}
        if resume:
            self._restore()
        elif cfg.init_from:
            path = checkpoint_path(cfg.init_from)
            load_weights(self.ac, path, self.env)
            log.info("initialised the policy from %s", path)

    # ------------------------------------------------------------------ data
    def _shard_path(self, r: int) -> Path:
        return self.run_dir / "data" / f"round_{r}.pt"

    def _label_round(self, r: int) -> tuple[dict[str, torch.Tensor], str]:
        """Round ``r``'s labelled states and a description."""
        cfg, kind = self.cfg, self.plan[r][0]
        bc = cfg.bc
        if kind == "demo":
            if self.plan[r][1] == 0:  # no demonstrations (a run that starts from init_from)
                return self._shard(self._empty_states()), "no demonstrations"
            targets, faces, what = _targets(cfg, self.rng, bc.objects, bc.seed)
            states = demonstrations(
                self.env,
                targets,
                dense=self.dense,
                overlap_limit=bc.overlap_limit,
                mirrored=faces,
                temperature=bc.temperature,
                generator=self.order_generator,
            )
            self.episodes += len(targets)
            return self._shard(states), what + (" in random orders" if self.free else "")
        if kind == "dagger":
            targets, faces, what = _targets(cfg, self.rng, bc.dagger_objects, bc.seed + r)
            states = demonstrations(
                self.env,
                targets,
                actor=policy_actor(self.policy),
                dense=self.dense,
                overlap_limit=bc.overlap_limit,
                mirrored=faces,
                temperature=bc.temperature,
            )
            self.episodes += len(targets)
            return self._shard(states), f"the policy's own assemblies of {what}"
        ex = cfg.exit
        targets, faces, what = _targets(cfg, self.rng, ex.objects, bc.seed + 1000 + r)
        planner = Lookahead(self.policy, ex.k)
        self.ac.eval()
        lab, chosen = planner.label(self.env, targets, faces, on_state=self._state_label)
        greedy = evaluate(self.env, targets, policy_actor(self.policy), mirrored=faces)
        planned = evaluate(self.env, targets, planner.replay(chosen, self.env), mirrored=faces)
        self.ac.train()
        self.episodes += len(targets)
        agree = float((lab.best == 0).float().mean())
        self.round_metrics = {
            "greedy_rela": float(greedy.rela.mean()),
            "planner_rela": float(planned.rela.mean()),
            "agreement": agree,
        }
        log.info(
            "expert-iteration round %d: on its %d objects the greedy policy scores Rela %.3f, the planner "
            "around it %.3f; the policy's mode is the planner's choice on %.1f %% of %d states",
            r,
            len(targets),
            greedy.rela.mean(),
            planned.rela.mean(),
            100 * agree,
            len(lab),
        )
        assert lab.extra is not None  # on_state labelled every state
        if self.free:
            assert isinstance(lab.extra, dict) and lab.remaining is not None  # free order records both
            states = {"observation": lab.observation, **lab.extra, "remaining": lab.remaining}
        else:
            assert isinstance(lab.extra, dict)  # _set_order_label's parts
            states = {"observation": lab.observation, **lab.extra}
        return self._shard(states, lab.candidates, lab.iou), f"the planner's assemblies of {what}"

    def _state_label(self, env: TangramEnv, rows: np.ndarray) -> dict[str, torch.Tensor]:
        """The label of worlds ``rows`` in their current state (:func:`_set_order_label`); with free order
        :func:`free_label`'s parts and the pieces each may choose."""
        bc = self.cfg.bc
        if self.free:
            label = free_label(env, bc.overlap_limit, bc.temperature, rows)
            return label | {"choosable": torch.as_tensor(env.choosable()[rows])}
        return _set_order_label(env, self.dense, bc.overlap_limit, rows)

    def _empty_states(self) -> dict[str, torch.Tensor]:
        g, v, p = self.env.grid, self.env.view, self.env.num_pieces
        obs = torch.zeros(0, 2, v.size, v.size, dtype=torch.uint8)
        if self.free:
            top = FREE_LABEL_TOP
            return {
                "observation": obs,
                "label": torch.zeros(0, top, dtype=torch.int32),
                "label_coverage": torch.zeros(0, top, dtype=torch.uint8),
                "label_rest": torch.zeros(0),
                "remaining": torch.zeros(0, p, dtype=torch.bool),
                "choosable": torch.zeros(0, p, dtype=torch.bool),
            }
        shape, dtype = ((0, g.norient, g.ny, g.nx), torch.uint8) if self.dense else ((0, len(g.nvec)), torch.int64)
        out = {"observation": obs, "label": torch.zeros(shape, dtype=dtype)}
        if self.dense and g.refined:
            out["fine_label"] = torch.zeros(0, len(g.nvec), dtype=torch.int64)
        return out

    def _shard(
        self, states: dict[str, torch.Tensor], candidates: torch.Tensor | None = None, iou: torch.Tensor | None = None
    ) -> dict[str, torch.Tensor]:
        k, n = self.cfg.exit.k, len(states["observation"])
        if candidates is None or iou is None:
            # A candidate is an env action: (x, y, orientation), with free order the piece first,
            # on a refined grid the offset last.
            candidates = torch.zeros(n, k, self.env.action_spec.shape[-1], dtype=torch.int64)
            iou = torch.full((n, k), float("nan"))
        return {**states, "candidates": candidates, "iou": iou}

    def _load_or_label(self, r: int) -> None:
        """Round ``r``'s data: from its shard if an earlier attempt wrote it, else labelled now."""
        path = self._shard_path(r)
        self.round_metrics = {}
        if path.exists():
            try:
                shard = torch.load(path, weights_only=True)
            except Exception as e:  # torch raises many types for truncated or foreign files
                raise CheckpointError(
                    f"{path}: not a readable data shard ({type(e).__name__}: {str(e)[:160]})"
                ) from None
            if not isinstance(shard, dict) or set(shard) != set(self.keys):
                raise CheckpointError(f"{path}: not a data shard of this supervised run (keys {self.keys})")
            log.info("round %d: %d labelled states from %s", r, len(shard["observation"]), path)
        else:
            t0 = time.perf_counter()
            shard, what = self._label_round(r)
            write_atomic(path, lambda f: torch.save(shard, f))
            log.info(
                "round %d: %d labelled states from %s in %.0f s",
                r,
                len(shard["observation"]),
                what,
                time.perf_counter() - t0,
            )
        self.shards.append(shard)

    # ------------------------------------------------------------------ state
    def _state(self) -> dict:
        cfg = self.cfg
        return {
            **policy_header(self.env, config_to_dict(cfg.policy)),
            "config": config_to_dict(cfg),
            "model": self.ac.state_dict(),
            "optim": self.opt.state_dict(),
            "curriculum": {"stage": 0, "switched_at": -1},
            "iteration": len(self.rows),
            "frames": sum(len(s["observation"]) for s in self.shards),
            "episodes": self.episodes,
            "minutes": self.minutes,
            # No CUDA generator state: an epoch draws its permutation on the CPU and nothing on the device.
            "rng": {"torch": torch.get_rng_state(), "numpy": self.rng.bit_generator.state},
            "supervision": {"round": self.round, "epoch": self.epoch, "rows": self.rows},
        }

    def _save(self) -> None:
        save_checkpoint(self.ckpt, self._state())
        fields = METRIC_FIELDS
        write_atomic(
            self.run_dir / "metrics.csv",
            ",".join(fields)
            + "\n"
            + "".join(
                ",".join(f"{r[k]:.6f}" if isinstance(r.get(k), float) else str(r.get(k, "")) for k in fields) + "\n"
                for r in self.rows
            ),
        )

    def _restore(self) -> None:
        st = load_weights(self.ac, self.ckpt, self.env)
        sup = st.get("supervision")
        if not isinstance(sup, dict) or "optim" not in st:
            raise CheckpointError(f"{self.ckpt}: not a checkpoint of a supervised run (no round and epoch)")
        try:
            self.opt.load_state_dict(st["optim"])
        except (RuntimeError, KeyError, ValueError) as e:
            raise CheckpointError(f"{self.ckpt}: optimiser state does not fit this policy ({str(e)[:200]})") from None
        self.round, self.epoch, self.rows = sup["round"], sup["epoch"], list(sup["rows"])
        self.episodes, self.minutes = st["episodes"], st["minutes"]
        torch.set_rng_state(st["rng"]["torch"])
        self.rng.bit_generator.state = st["rng"]["numpy"]
        for r in range(self.round + 1):
            if not self._shard_path(r).exists():
                raise CheckpointError(
                    f"{self._shard_path(r)}: the data of round {r} is missing; the run cannot resume without it"
                )
            self._load_or_label(r)
        log.info("resumed %s at round %d, epoch %d", self.ckpt, self.round, self.epoch)

    # ------------------------------------------------------------------ learning
    def _inputs(self, data: dict[str, torch.Tensor], idx: torch.Tensor) -> TensorDict:
        """What the policy reads of states ``idx``: the image, and with free order the pieces left
        and the action mask (the choosable pieces; every x, y and orientation allowed)."""
        td = TensorDict(observation=data["observation"][idx], batch_size=[len(idx)])
        if self.free:
            td.update(free_order_inputs(data["remaining"][idx], data["choosable"][idx], self.env.grid))
        return td.to(self.device)

    def _fit_epoch(self, data: dict[str, torch.Tensor], planned: int, sup_weight: float = 1.0) -> dict:
        cfg, bc = self.cfg, self.cfg.bc
        n = len(data["observation"])
        perm = torch.randperm(n)
        sums = {"loss": 0.0, "sup": 0.0, "rank": 0.0}
        ranked = 0
        for i in range(0, n, bc.minibatch_size):
            idx = perm[i : i + bc.minibatch_size]
            for group in self.opt.param_groups:
                group["lr"] = cfg.optim.learning_rate((len(self.rows) + i / n) / planned)
            # The labelled data stays on the CPU (it can be large); minibatches go to the device.
            iou = data["iou"][idx].to(self.device)
            with autocast(cfg.precision, self.device):
                dist = self.policy.get_dist(self._inputs(data, idx))
                # With weight 0 the supervised loss is only logged: no backward pass through it.
                with torch.set_grad_enabled(sup_weight > 0 and torch.is_grad_enabled()):
                    label = data["label"][idx].to(self.device)
                    if self.free:
                        sup = free_supervised_loss(
                            dist,
                            label,
                            data["label_coverage"][idx].to(self.device),
                            data["label_rest"][idx].to(self.device),
                            bc.temperature,
                        ).mean()
                    else:
                        sup = supervised_loss(dist, label, self.dense, bc.temperature).mean()
                    if "fine_label" in data:
                        sup = sup - dist.fine_log_prob(data["fine_label"][idx].to(self.device)).mean()
                has = ~iou[:, 0].isnan()
                rank = torch.zeros((), device=self.device)
                if has.any():
                    rank = ranking_loss(
                        dist, data["candidates"][idx].to(self.device)[has], iou[has], cfg.exit.temperature
                    ).sum() / len(idx)
                loss = sup_weight * sup + cfg.exit.weight * rank
            self.opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(self.ac.parameters(), cfg.optim.max_grad_norm)
            self.opt.step()
            m = len(idx)
            sums["loss"] += loss.item() * m
            sums["sup"] += sup.item() * m
            sums["rank"] += rank.item() * m
            ranked += int(has.sum())
        return {k: v / max(n, 1) for k, v in sums.items()} | {"samples": n, "ranked": ranked}

    def run(self, n_eval: int = 100) -> dict:
        """Label and fit every round from where the run stands, then evaluate the policy greedily on
        ``n_eval`` Random objects (0: no evaluation); returns a summary."""
        t0 = time.perf_counter() - self.minutes * 60
        planned = max(1, sum(e for _, e in self.plan))
        if not self.shards:
            self._load_or_label(0)
        while True:
            kind, epochs = self.plan[self.round]
            data = {k: torch.cat([s[k] for s in self.shards]) for k in self.keys}
            while self.epoch < epochs:
                res = self._fit_epoch(data, planned, self.cfg.exit.dense if kind == "exit" else 1.0)
                self.epoch += 1
                self.minutes = (time.perf_counter() - t0) / 60
                row = {
                    "epoch": len(self.rows) + 1,
                    "round": self.round,
                    "kind": kind,
                    **res,
                    "lr": self.opt.param_groups[0]["lr"],
                    "minutes": self.minutes,
                    **(self.round_metrics if self.epoch == 1 else {}),
                }
                self.rows.append(row)
                log.info(
                    "epoch %d (round %d, %s, %d samples): loss %.4f (supervised %.4f, ranking %.4f)",
                    len(self.rows),
                    self.round,
                    kind,
                    res["samples"],
                    res["loss"],
                    res["sup"],
                    res["rank"],
                )
                self._save()
            del data
            # Each round's policy stays loadable: the next round's planner is built around it.
            save_checkpoint(self.ckpt.with_name(f"round{self.round}.pt"), self._state())
            if self.round + 1 >= len(self.plan):
                break
            self.round, self.epoch = self.round + 1, 0
            self._load_or_label(self.round)
            self._save()  # the round's data is written: a resume starts its epochs
        if not self.ckpt.exists():  # a run without epochs (init_from's weights, evaluated) leaves one too
            self._save()
        ev = {}
        if n_eval > 0:
            ev = evaluate_random(self.policy, self.cfg.env_config(), n=n_eval)
            write_atomic(self.run_dir / "eval.json", json.dumps(ev, indent=1) + "\n")
        samples = sum(len(s["observation"]) for s in self.shards)
        return {
            "samples": samples,
            "what": f"{len(self.plan)} rounds",
            "loss": self.rows[-1]["loss"] if self.rows else float("nan"),
            **ev,
        }


#: Columns of a supervised run's ``metrics.csv``: one row per epoch; the planner's figures
#: (greedy and planner Rela on the round's objects, how often the policy's mode is the planner's
#: choice) on the first epoch of an expert-iteration round.
METRIC_FIELDS = [
    "epoch",
    "round",
    "kind",
    "samples",
    "ranked",
    "loss",
    "sup",
    "rank",
    "lr",
    "minutes",
    "greedy_rela",
    "planner_rela",
    "agreement",
]


def train_bc(cfg: TrainConfig, run_dir: Path, resume: bool = False, n_eval: int = 100) -> dict:
    """Train the configured network by supervision (see :class:`SupervisedRun`); writes a
    checkpoint like PPO's after every epoch, and evaluates on ``n_eval`` Random objects."""
    return SupervisedRun(cfg, run_dir, resume=resume).run(n_eval)
