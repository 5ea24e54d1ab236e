"""The afterstate re-ranker: the spatial policy proposes its k best placements, a second network
with a view of the whole image picks one.

At every step the candidates are the spatial policy's own top k (``GridCategorical.top_modes``:
with a mode window, k separate peaks). Each candidate's piece footprint is drawn into the current
view (a raster of the piece at the candidate's pose: no simulation, nothing but the observation),
and a small CNN scores [silhouette, view, footprint] from the whole image, plus a learnt multiple
of the policy's own score so that it starts from the policy's order. The best candidate goes. The
spatial policy scores each cell from about 13 cm of context; which of two distant placements
leaves a silhouette the rest can fill needs the whole image.

It learns the lookahead planner's judgement (:mod:`mrchaos.learn.planner`): the data shards of
expert-iteration runs keep, for every planned state, the policy's candidates and the silhouette
IoU that each one's greedy completion reached. The loss is the listwise cross-entropy between
softmax(IoU / T) and the re-ranker's softmax over the same candidates; the policy stays frozen.
A re-ranked checkpoint is the policy's checkpoint plus ``ranker`` weights; the bench plays it as
one policy (``algo: rerank``).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from tensordict import TensorDict
from torch import nn

from mrchaos.core.atomic import write_atomic
from mrchaos.core.raster import View, rasterize
from mrchaos.env.actions import ActionGrid
from mrchaos.env.tangram import FREE_ORDER_KEYS, TangramEnv, free_order_inputs
from mrchaos.figures.pieces import PieceSet, get_piece_set
from mrchaos.learn.checkpoint import (
    CheckpointError,
    checkpoint_path,
    load_checkpoint,
    load_weights,
    policy_header,
    save_checkpoint,
)
from mrchaos.learn.config import RerankConfig, TrainConfig, config_to_dict, load_config, start_run
from mrchaos.learn.evaluate import evaluate_random, policy_device
from mrchaos.learn.policy import GridCategorical, PolicyConfig, build_actor_critic

__all__ = [
    "AfterstateRanker",
    "Reranked",
    "candidate_footprints",
    "planner_states",
    "judge",
    "listwise_loss",
    "reranked_actor",
    "train_rerank",
    "RERANK_FIELDS",
]

log = logging.getLogger("mrchaos.learn.rerank")

#: Columns of a re-ranker run's ``metrics.csv``, one row per epoch: the loss, and on the training
#: and held-out states the agreement with the planner (the top-scored candidate reaches the best
#: completion's IoU) and the mean IoU regret.
RERANK_FIELDS = [
    "epoch",
    "samples",
    "loss",
    "train_agreement",
    "train_regret",
    "held_agreement",
    "held_regret",
    "minutes",
]


class AfterstateRanker(nn.Module):
    """Scores candidates from [silhouette, view, candidate footprint]: the images average-pooled by 2
    (4.3 mm pixels), four stride-2 convolutions to a 4 x 4 map of the whole view (about 7 cm cells),
    an MLP over all of it, plus a learnt multiple (``prior``) of the policy's own score."""

    def __init__(self, width: int = 32, size: int = 120) -> None:
        super().__init__()
        w = width
        self.conv = nn.Sequential(
            nn.Conv2d(3, w, 5, stride=2, padding=2),
            nn.ReLU(),
            nn.Conv2d(w, 2 * w, 3, stride=2, padding=1),
            nn.ReLU(),
            nn.Conv2d(2 * w, 2 * w, 3, stride=2, padding=1),
            nn.ReLU(),
            nn.Conv2d(2 * w, 2 * w, 3, stride=2, padding=1),
            nn.ReLU(),
        )
        cells = -(-size // 32)  # the pooled image halved four times
        self.head = nn.Sequential(nn.Flatten(), nn.Linear(2 * w * cells * cells, 256), nn.ReLU(), nn.Linear(256, 1))
        self.prior = nn.Parameter(torch.ones(()))

    def forward(self, obs: torch.Tensor, footprints: torch.Tensor, prior: torch.Tensor) -> torch.Tensor:
        """(B, k) scores of ``footprints`` (B, k, H, W) bool in ``obs`` (B, 2, H, W) uint8, given the
        policy's scores ``prior`` (B, k)."""
        b, k = footprints.shape[:2]
        x = torch.cat(
            [obs[:, None].expand(b, k, 2, *obs.shape[-2:]).float() / 255, footprints[:, :, None].float()], 2
        ).reshape(b * k, 3, *obs.shape[-2:])
        x = F.avg_pool2d(x, 2)
        return self.head(self.conv(x)).reshape(b, k) + self.prior * prior


def candidate_footprints(
    piece_set: PieceSet, grid: ActionGrid, view: View, candidates: torch.Tensor, piece: torch.Tensor | None = None
) -> torch.Tensor:
    """(S, k, H, W) bool: each candidate's piece footprint, rasterised in the view where the
    candidate puts it, turned over where its orientation index says so. ``candidates`` (S, k, 3)
    are grid actions of ``piece[s]`` (the set's order), or (S, k, 4) name their piece first (free
    order, where ``piece`` is not needed)."""
    s, k = candidates.shape[:2]
    if candidates.shape[-1] == 4:
        which = candidates[..., 0].reshape(-1).cpu().numpy()
        act = candidates[..., 1:].reshape(-1, 3).cpu().numpy()
    else:
        if piece is None:
            raise ValueError("grid actions (x, y, orientation) need the piece they place")
        which = np.repeat(piece.cpu().numpy(), k)
        act = candidates.reshape(-1, 3).cpu().numpy()
    rows = np.arange(len(act))
    mirrored = grid.mirrored(act) & piece_set.chiral[which]
    poses = np.zeros((len(act), len(piece_set), 3))
    poses[rows, which] = piece_set.to_centroid(which, grid.to_pose(act), mirrored)
    faces = np.zeros((len(act), len(piece_set)), dtype=bool)
    faces[rows, which] = mirrored
    visible = np.zeros((len(act), len(piece_set)), dtype=bool)
    visible[rows, which] = True
    out = []
    for i in range(0, len(act), 4096):  # bounded memory for the rasteriser's buffers
        sl = slice(i, i + 4096)
        polys = piece_set.footprints(poses[sl], faces[sl])
        out.append(torch.as_tensor(rasterize(polys, view, visible=visible[sl], parts=piece_set.raster_parts).ids >= 0))
    return torch.cat(out).reshape(s, k, view.size, view.size)


def planner_states(run: Path, extra: tuple[str, ...] = ()) -> list[dict[str, torch.Tensor]]:
    """The planner-labelled states of an expert-iteration run, one dict per data shard that has
    them (in round order): ``observation``, ``candidates``, ``iou``, ``step`` (how many pieces were
    placed before the state: the piece it places in the set's order), with free order the policy's
    other inputs (``remaining``, ``choosable``), and the shard keys in ``extra`` (e.g. ``label``,
    the dense targets)."""
    if not (run / "config.yaml").exists():
        raise CheckpointError(f"{run}: not a run folder (no config.yaml)")
    cfg = load_config(run / "config.yaml")
    per_chunk = cfg.env.num_worlds // cfg.exit.k  # targets the planner holds at once
    paths = sorted((run / "data").glob("round_*.pt"), key=lambda q: int(q.stem.split("_")[1]))
    p = len(get_piece_set(cfg.env.piece_set))
    # Free order: what the policy reads beside the image, to score the candidates again.
    inputs = ("remaining", "choosable") if cfg.env.order == "free" else ()
    out: list[dict[str, torch.Tensor]] = []
    for path in paths:
        try:
            shard = torch.load(path, weights_only=True)
            keep = ~shard["iou"][:, 0].isnan()
        except Exception as e:  # a truncated or foreign file
            raise CheckpointError(f"{path}: not a data shard ({type(e).__name__}: {str(e)[:120]})") from None
        n = int(keep.sum())
        if n == 0:
            continue  # demonstrations and DAgger: no planner judgement
        # The planner's rows run (chunk, step, target) with per_chunk targets a chunk, the last maybe short.
        objects = n // p
        step = torch.cat(
            [torch.arange(p).repeat_interleave(min(per_chunk, objects - c)) for c in range(0, objects, per_chunk)]
        )
        if len(step) != n:
            raise CheckpointError(f"{path}: {n} planned states are not whole episodes of {p} pieces")
        out.append({k: shard[k][keep] for k in ("observation", "candidates", "iou", *inputs, *extra)})
        out[-1]["step"] = step
    if not out:
        raise CheckpointError(f"{run / 'data'}: no data shard with planner-labelled states (exit.rounds: 0?)")
    return out


def listwise_loss(scores: torch.Tensor, iou: torch.Tensor, temperature: float) -> torch.Tensor:
    """Per-state cross-entropy between softmax(IoU / T) over a state's candidates (B, k) and
    softmax(``scores``) of the same candidates (a re-ranker's, or the policy's own in expert
    iteration: :func:`mrchaos.learn.bc.ranking_loss`)."""
    target = torch.softmax(iou / temperature, -1)
    return -(target * F.log_softmax(scores, -1)).sum(-1)


def judge(scores: torch.Tensor, iou: torch.Tensor) -> tuple[float, float]:
    """Agreement with the planner (the top-scored candidate reaches the best IoU; ties count) and the
    mean IoU regret."""
    pick = scores.argmax(1)
    regret = iou.max(1).values - iou.gather(1, pick[:, None]).squeeze(1)
    return float((regret <= 1e-6).float().mean()), float(regret.mean())


class Reranked:
    """An actor (:data:`mrchaos.learn.evaluate.Actor`): the spatial policy's top k, re-ranked."""

    def __init__(self, policy, ranker: AfterstateRanker, k: int) -> None:
        self.policy, self.ranker, self.k = policy, ranker.eval(), k

    def scores(self, env: TangramEnv, td: TensorDict) -> tuple[torch.Tensor, torch.Tensor]:
        """Each world's candidates (N, k, 3), with free order (N, k, 4) naming the piece first, and
        the re-ranker's scores of them (N, k)."""
        device = policy_device(self.policy)
        with torch.no_grad():
            inputs = td.select("observation", *FREE_ORDER_KEYS, strict=False).to(device)
            dist = self.policy.get_dist(inputs)
            if not isinstance(dist, GridCategorical):
                raise ValueError("a re-ranker needs a spatial policy (one score per grid action)")
            cand = dist.top_actions(self.k)
            piece = None if env.free_order else torch.as_tensor(env.next_piece).clamp_max(env.num_pieces - 1)
            foot = candidate_footprints(env.piece_set, env.grid, env.view, cand, piece).to(device)
            return cand, self.ranker(inputs["observation"], foot, dist.scores_at(cand))

    def ranked(self, env: TangramEnv, td: TensorDict) -> torch.Tensor:
        """(N, k, 3) each world's candidates ((N, k, 4) with free order) in the re-ranker's order,
        best first (ties keep the policy's order)."""
        cand, s = self.scores(env, td)
        order = torch.sort(s, dim=1, descending=True, stable=True).indices
        return cand.gather(1, order[..., None].expand_as(cand))

    def __call__(self, env: TangramEnv, td: TensorDict) -> torch.Tensor:
        cand, s = self.scores(env, td)
        return cand[torch.arange(len(cand)), s.argmax(1)].to(env.device)


def reranked_actor(state: dict, policy, view: View) -> Reranked | None:
    """The re-ranked actor of a checkpoint with ``ranker`` weights around its ``policy`` module (None
    for a checkpoint without them); :class:`CheckpointError` when the weights do not fit."""
    if "ranker" not in state:
        return None
    rc = RerankConfig(**state.get("config", {}).get("rerank", {}))
    ranker = AfterstateRanker(rc.width, view.size)
    try:
        ranker.load_state_dict(state["ranker"])
    except (RuntimeError, KeyError) as e:
        raise CheckpointError(f"re-ranker weights do not fit rerank.width {rc.width} ({str(e)[:160]})") from None
    return Reranked(policy, ranker.to(policy_device(policy)), rc.k)


class RerankRun:
    """Fits a re-ranker around a frozen spatial policy (``init_from``) on the planner-labelled states
    of expert-iteration runs (``rerank.data``; the last ``rerank.held_out`` shards only measure).
    Every epoch rewrites ``checkpoints/last.pt`` (the policy, the re-ranker, its optimiser, RNG and
    the epoch) and ``metrics.csv`` atomically, so ``resume`` continues after the last epoch."""

    def __init__(self, cfg: TrainConfig, run_dir: Path, resume: bool = False) -> None:
        rc = cfg.rerank
        if not cfg.init_from:
            raise ValueError("algo: rerank re-ranks a trained spatial policy: set init_from")
        if cfg.policy.name != "spatial":
            raise ValueError("algo: rerank needs the spatial policy (the candidates are its top k)")
        if not rc.data:
            raise ValueError("rerank.data must name the expert-iteration runs whose planner data it learns from")
        # The network is the initial policy's: its own config, whatever the file says.
        init = checkpoint_path(cfg.init_from)
        cfg = dataclasses.replace(cfg, policy=PolicyConfig(**load_checkpoint(init)["policy"]))
        self.cfg, self.run_dir = cfg, Path(run_dir)
        self.ckpt = start_run(cfg, self.run_dir, resume)
        self.env = TangramEnv(dataclasses.replace(cfg.env_config(), task=cfg.task.given_targets()), seed=cfg.seed)
        # Free order: the policy also reads the pieces left and proposes (piece, x, y, orientation).
        pieces = self.env.num_pieces if self.env.free_order else 0
        self.ac = build_actor_critic(cfg.policy, self.env.grid, self.env.view, self.env.action_spec, pieces)
        load_weights(self.ac, init, self.env)
        self.ac.eval()
        self.policy = self.ac.get_policy_operator()
        self.ranker = AfterstateRanker(rc.width, self.env.view.size)
        self.opt = torch.optim.Adam(self.ranker.parameters(), lr=rc.lr)
        self.rows: list[dict] = []
        self.minutes = 0.0
        if resume:
            st = load_checkpoint(self.ckpt)
            if "ranker" not in st or "rerank_optim" not in st:
                raise CheckpointError(f"{self.ckpt}: not a checkpoint of a re-ranker run")
            self.ranker.load_state_dict(st["ranker"])
            self.opt.load_state_dict(st["rerank_optim"])
            self.rows, self.minutes = list(st["rerank_rows"]), st["minutes"]
            torch.set_rng_state(st["rng"]["torch"])

    def _load(self) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor] | None]:
        """The training and the held-out states (the last ``held_out`` shards), with each
        candidate's footprint and the policy's score of it."""
        rc = self.cfg.rerank
        shards = [s for r in rc.data for s in planner_states(Path(r))]
        if len(shards) <= rc.held_out:
            raise ValueError(f"rerank.held_out {rc.held_out} leaves none of the {len(shards)} shards of {rc.data}")
        k = shards[0]["candidates"].shape[1]
        if k != rc.k:
            raise ValueError(f"rerank.k is {rc.k}, but the planner of {rc.data} kept {k} candidates")
        cut = len(shards) - rc.held_out
        return self._prepare(shards[:cut]), self._prepare(shards[cut:]) if rc.held_out else None

    def _prepare(self, shards: list[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
        data = {key: torch.cat([s[key] for s in shards]) for key in shards[0]}
        e = self.env
        # In the set's order a state's step is its piece; free order's candidates name theirs.
        piece = None if e.free_order else data["step"]
        data["footprints"] = candidate_footprints(e.piece_set, e.grid, e.view, data["candidates"], piece)
        data["prior"] = self._prior(data)
        return data

    def _prior(self, data: dict[str, torch.Tensor]) -> torch.Tensor:
        """The frozen policy's scores at the candidates (computed once)."""
        out = []
        with torch.no_grad():
            for i in range(0, len(data["iou"]), 512):
                sl = slice(i, i + 512)
                td = TensorDict(observation=data["observation"][sl], batch_size=[len(data["observation"][sl])])
                if self.env.free_order:
                    td.update(free_order_inputs(data["remaining"][sl], data["choosable"][sl], self.env.grid))
                out.append(self.policy.get_dist(td).scores_at(data["candidates"][sl]))
        return torch.cat(out)

    def _scores(self, data: dict[str, torch.Tensor]) -> torch.Tensor:
        with torch.no_grad():
            return torch.cat(
                [
                    self.ranker(
                        data["observation"][i : i + 512], data["footprints"][i : i + 512], data["prior"][i : i + 512]
                    )
                    for i in range(0, len(data["iou"]), 512)
                ]
            )

    def _state(self) -> dict:
        cfg = self.cfg
        return {
            **policy_header(self.env, config_to_dict(cfg.policy)),
            "config": config_to_dict(cfg),
            "model": self.ac.state_dict(),
            "ranker": self.ranker.state_dict(),
            "rerank_optim": self.opt.state_dict(),
            "rerank_rows": self.rows,
            # The counters every checkpoint carries (a re-ranker run has epochs, not iterations).
            "curriculum": {"stage": 0, "switched_at": -1},
            "iteration": len(self.rows),
            "frames": self.rows[-1]["samples"] if self.rows else 0,
            "episodes": 0,
            "minutes": self.minutes,
            "rng": {"torch": torch.get_rng_state()},
        }

    def _save(self) -> None:
        save_checkpoint(self.ckpt, self._state())
        write_atomic(
            self.run_dir / "metrics.csv",
            ",".join(RERANK_FIELDS)
            + "\n"
            + "".join(
                ",".join(f"{r[k]:.6f}" if isinstance(r[k], float) else str(r[k]) for k in RERANK_FIELDS) + "\n"
                for r in self.rows
            ),
        )

    def run(self, n_eval: int = 100) -> dict:
        """Fit the remaining epochs, then play ``n_eval`` held-out Random objects greedily (0: none);
        a summary."""
        rc = self.cfg.rerank
        t0 = time.perf_counter() - self.minutes * 60
        train, held = self._load()
        n = len(train["iou"])
        log.info("%d training states, %d held-out", n, 0 if held is None else len(held["iou"]))
        while len(self.rows) < rc.epochs:
            perm = torch.randperm(n)
            total = 0.0
            for i in range(0, n, rc.batch):
                idx = perm[i : i + rc.batch]
                s = self.ranker(train["observation"][idx], train["footprints"][idx], train["prior"][idx])
                loss = listwise_loss(s, train["iou"][idx], rc.temperature).mean()
                self.opt.zero_grad(set_to_none=True)
                loss.backward()
                self.opt.step()
                total += loss.item() * len(idx)
            self.minutes = (time.perf_counter() - t0) / 60
            ta, tr = judge(self._scores(train), train["iou"])
            ha, hr = judge(self._scores(held), held["iou"]) if held is not None else (float("nan"), float("nan"))
            row = {
                "epoch": len(self.rows) + 1,
                "samples": n,
                "loss": total / n,
                "train_agreement": ta,
                "train_regret": tr,
                "held_agreement": ha,
                "held_regret": hr,
                "minutes": self.minutes,
            }
            self.rows.append(row)
            held_note = f", {100 * ha:.1f} % held out" if held is not None else " (none held out)"
            log.info("epoch %d: loss %.4f, agreement %.1f %% train%s", row["epoch"], row["loss"], 100 * ta, held_note)
            self._save()
        ev = {}
        if n_eval > 0:
            played = Reranked(self.policy, self.ranker, self.cfg.rerank.k)
            ev = evaluate_random(played, self.cfg.env_config(), n=n_eval)
            write_atomic(self.run_dir / "eval.json", json.dumps(ev, indent=1) + "\n")
        return {"samples": n, "what": f"{rc.epochs} epochs of re-ranking", "loss": self.rows[-1]["loss"], **ev}


def train_rerank(cfg: TrainConfig, run_dir: Path, resume: bool = False, n_eval: int = 100) -> dict:
    """Fit the afterstate re-ranker around a trained spatial policy (see :class:`RerankRun`), then
    evaluate the re-ranked policy on ``n_eval`` Random objects (0: no evaluation)."""
    return RerankRun(cfg, run_dir, resume=resume).run(n_eval)
