"""Which network can learn the planner's ranking? Fit against generalisation on planner-labelled states.

Reads the data shards of expert-iteration runs (``runs/<name>/data/round_R.pt``: each state, the
policy's top-k candidates and the silhouette IoU of each one's greedy completion), trains a
network to rank the candidates as the planner does (the listwise loss of
:func:`mrchaos.learn.bc.ranking_loss`), and prints, per epoch, on the training states and on
held-out ones (other chaos objects):

* agreement: the share of states whose top-ranked candidate reaches the planner's best IoU
  (candidates whose completions tie count alike);
* regret: the IoU the planner's choice reaches minus that of the network's choice (mean).

Networks (``--net``):

* ``policy``: the spatial policy itself (from ``--init``), its windowed mode scores at the
  candidates, ranking loss only (``--dense W`` adds W x the dense loss of the same states);
* ``afterstate``: a separate re-ranker with a global view, scoring each candidate from the
  silhouette, the view and the candidate piece's footprint drawn into it (no simulation), plus
  the policy's own score as a prior; ``--width`` sets its channels.

At the end, ``--eval N`` plays N held-out Random objects (seed ``--seed``) greedily with the
result (for ``afterstate``, the policy's top-k re-ranked) and prints Rela / Final.

    python tools/ranking_fit.py --train runs/lab_train --held runs/lab_heldout --net policy --epochs 10
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict

from mrchaos.env.tangram import TangramEnv
from mrchaos.learn.bc import ranking_loss, supervised_loss
from mrchaos.learn.checkpoint import checkpoint_path, load_checkpoint
from mrchaos.learn.config import config_from_dict
from mrchaos.learn.evaluate import evaluate
from mrchaos.learn.policy import build_actor_critic, unravel_actions
from mrchaos.learn.rerank import AfterstateRanker, candidate_footprints, judge, listwise_loss, planner_states
from mrchaos.tasks.chaos import generate


def load_states(run: Path) -> dict[str, torch.Tensor]:
    """The planner-labelled states of a run's shards, with each state's step (piece index)."""
    shards = planner_states(run, extra=("label",))
    return {k: torch.cat([s[k] for s in shards]) for k in shards[0]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--train", type=Path, nargs="+", required=True, help="runs whose shards train")
    ap.add_argument("--held", type=Path, nargs="+", required=True, help="runs whose shards are held out")
    ap.add_argument("--init", default="mrchaos-dense", help="the policy (a shipped name, a run or a file)")
    ap.add_argument("--net", choices=["policy", "afterstate"], default="policy")
    ap.add_argument("--dense", type=float, default=0.0, help="policy: weight of the dense loss beside the ranking")
    ap.add_argument(
        "--rank",
        type=float,
        default=1.0,
        help="policy: weight of the ranking loss (0: the dense loss alone on the planner's states, a control)",
    )
    ap.add_argument("--width", type=int, default=32)
    ap.add_argument("--epochs", type=int, default=10)
    ap.add_argument("--lr", type=float, default=3e-4)
    ap.add_argument("--batch", type=int, default=128)
    ap.add_argument("--temperature", type=float, default=0.01)
    ap.add_argument("--limit", type=int, default=0, help="train on the first N states only (0: all)")
    ap.add_argument("--eval", type=int, default=200)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--save", type=Path, help="afterstate: write the trained re-ranker's weights here")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)

    path = checkpoint_path(args.init)
    st = load_checkpoint(path)
    cfg = config_from_dict(st["config"])
    env = TangramEnv(dataclasses.replace(cfg.env_config(), task=cfg.task.given_targets()), seed=0)
    ac = build_actor_critic(cfg.policy, env.grid, env.view, env.action_spec)
    ac.load_state_dict(st["model"])
    policy = ac.get_policy_operator()
    sets = {}
    for name, runs in (("train", args.train), ("held", args.held)):
        parts = [load_states(r) for r in runs]
        sets[name] = {k: torch.cat([p[k] for p in parts]) for k in parts[0]}
    if args.limit:
        sets["train"] = {k: v[: args.limit] for k, v in sets["train"].items()}
    print(f"{len(sets['train']['iou'])} training states, {len(sets['held']['iou'])} held-out; net {args.net}")

    def policy_scores(obs: torch.Tensor, cand: torch.Tensor, grad: bool = False):
        with torch.set_grad_enabled(grad):
            dist = policy.get_dist(TensorDict(observation=obs, batch_size=[len(obs)]))
            return dist, dist.scores_at(cand)

    def all_scores(data: dict, model=None) -> torch.Tensor:
        out = []
        for i in range(0, len(data["iou"]), 512):
            sl = slice(i, i + 512)
            _, s = policy_scores(data["observation"][sl], data["candidates"][sl])
            if model is not None:
                with torch.no_grad():
                    s = model(data["observation"][sl], data["masks"][sl], s)
            out.append(s)
        return torch.cat(out)

    ranker = None
    if args.net == "afterstate":
        t0 = time.perf_counter()
        for d in sets.values():
            d["masks"] = candidate_footprints(env.piece_set, env.grid, env.view, d["candidates"], d["step"])
        print(f"candidate footprints drawn in {time.perf_counter() - t0:.0f} s")
        ranker = AfterstateRanker(args.width, env.view.size)
        params = list(ranker.parameters())
    else:
        params = list(ac.parameters())
    opt = torch.optim.Adam(params, lr=args.lr)
    for name, d in sets.items():
        a, r = judge(all_scores(d), d["iou"])
        print(f"before: {name} agreement {100 * a:.1f} %, regret {r:.4f}")
    train = sets["train"]
    n = len(train["iou"])
    for epoch in range(1, args.epochs + 1):
        t0 = time.perf_counter()
        perm = torch.randperm(n)
        for i in range(0, n, args.batch):
            idx = perm[i : i + args.batch]
            obs, cand, iou = train["observation"][idx], train["candidates"][idx], train["iou"][idx]
            if ranker is None:
                dist, s = policy_scores(obs, cand, grad=True)
                loss = args.rank * ranking_loss(dist, cand, iou, args.temperature).mean()
                if args.dense:
                    loss = loss + args.dense * supervised_loss(dist, train["label"][idx], True, 0.01).mean()
            else:
                _, prior = policy_scores(obs, cand)
                s = ranker(obs, train["masks"][idx], prior)
                loss = listwise_loss(s, iou, args.temperature).mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
        cells = []
        for name, d in sets.items():
            a, r = judge(all_scores(d, ranker), d["iou"])
            cells.append(f"{name} agreement {100 * a:.1f} %, regret {r:.4f}")
        print(f"epoch {epoch} ({time.perf_counter() - t0:.0f} s): " + "; ".join(cells), flush=True)

    if args.save is not None and ranker is not None:
        args.save.parent.mkdir(parents=True, exist_ok=True)
        torch.save({"ranker": ranker.state_dict(), "args": {k: str(v) for k, v in vars(args).items()}}, args.save)
        print(f"wrote {args.save}")

    if args.eval:
        targets, _, mirrored = generate(
            env.piece_set, args.eval, np.random.default_rng(args.seed), cfg.task.chaos, env.view
        )
        ev = TangramEnv(dataclasses.replace(cfg.env_config(), num_worlds=100, task=cfg.task.given_targets()), seed=0)
        k = train["candidates"].shape[1]

        def act(e: TangramEnv, td: TensorDict) -> torch.Tensor:
            with torch.no_grad():
                dist = policy.get_dist(td.select("observation").clone())
                if ranker is None:
                    return dist.mode
                top = dist.top_modes(k)
                _, y, x = dist.grid_shape
                cand = unravel_actions(top, x, y)
                step = torch.as_tensor(e.next_piece)
                foot = candidate_footprints(e.piece_set, e.grid, e.view, cand, step)
                s = ranker(td["observation"], foot, dist.scores_at(cand))
                return cand[torch.arange(len(cand)), s.argmax(1)]

        res = evaluate(ev, targets, act, mirrored=mirrored)
        print(
            f"greedy on {args.eval} Random objects (seed {args.seed}): Rela {100 * res.rela.mean():.1f} "
            f"Final {100 * res.final.mean():.1f}"
        )


if __name__ == "__main__":
    main()
