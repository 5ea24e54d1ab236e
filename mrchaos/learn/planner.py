"""The lookahead planner around a spatial policy: each placement chosen among the policy's top-k
actions by where greedy completions in the simulator end, scored on the silhouette alone (no
solution is read). It plays at test time (``mrchaos-bench --lookahead K``) and labels states for
training (expert iteration: :mod:`mrchaos.learn.bc` distils its ranking into the policy).

For every step t of an episode, k copies of the world replay the placements chosen so far, each
copy places the piece at one of the policy's k best actions (``GridCategorical.top_modes``: with a
mode window, k separate peaks), and the policy then completes the assembly greedily. With free order
(``env.order: free``) a candidate is (piece, x, y, orientation): the planner weighs which piece
goes next as well as where, and the completions follow the policy's own order. The candidate
whose completion reaches the highest IoU of the occupied area with the silhouette wins (ties go to
the policy's order, so k = 1 is the greedy policy). IoU is observable: the silhouette is the prompt
and the occupied area is the view. The planner uses the simulator as its model, so it is a planner
around the policy, not the policy alone, and the bench labels it so. The cost is about
k x pieces² env steps per episode instead of pieces; the env's worlds hold k copies of
``worlds // k`` targets at once.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch
from tensordict import TensorDict

from mrchaos.env.tangram import FREE_ORDER_KEYS, TangramEnv
from mrchaos.learn.evaluate import Actor, policy_device
from mrchaos.learn.policy import GridCategorical

if TYPE_CHECKING:  # the re-ranker module builds on this one's layer; only its type is needed here
    from mrchaos.learn.rerank import Reranked

__all__ = ["Lookahead", "PlannerLabels"]


@dataclass
class PlannerLabels:
    """What the planner saw and judged at every planned state, one row per (target, step).

    Attributes:
        observation: (S, 2, H, W) uint8, the state before the step (as the policy saw it).
        candidates: (S, k, 3) int64 grid actions (x, y, orientation), in the policy's order
            ((S, k, 4) with free order, the piece first; on a refined grid, the offset last).
        iou: (S, k) float32 silhouette IoU at the end of each candidate's greedy completion.
        step: (S,) int64 the step of the state (how many pieces were placed before it).
        extra: (S, ...) what ``on_state`` returned for the state (e.g. dense targets; a tensor, or
            a dict of tensors whose rows line up), or None.
        remaining: (S, P) bool with free order, the pieces not yet placed (what the policy reads
            beside the image), else None.
    """

    observation: torch.Tensor
    candidates: torch.Tensor
    iou: torch.Tensor
    step: torch.Tensor
    extra: torch.Tensor | dict[str, torch.Tensor] | None = None
    remaining: torch.Tensor | None = None

    @property
    def best(self) -> torch.Tensor:
        """(S,) index of the candidate the planner chose: the highest IoU, the first of ties."""
        return self.iou.argmax(1)

    def __len__(self) -> int:
        return len(self.step)


def _cat(parts: list) -> torch.Tensor | dict[str, torch.Tensor]:
    """Tensors, or dicts of tensors (``on_state``'s answers), joined along their rows."""
    if isinstance(parts[0], dict):
        return {key: torch.cat([p[key] for p in parts]) for key in parts[0]}
    return torch.cat(parts)


class Lookahead:
    """Plans whole episodes for a spatial policy (a ``GridCategorical`` over the grid's actions).

    With ``reranked`` (a :class:`mrchaos.learn.rerank.Reranked` around the same policy) the
    candidates are the re-ranker's k best of its own candidates, in its order, and the completions
    play the re-ranked policy: the planner around the policy as shipped."""

    def __init__(self, policy, k: int, reranked: Reranked | None = None) -> None:
        if k < 1:
            raise ValueError(f"lookahead k must be >= 1, got {k}")
        if reranked is not None and k > reranked.k:
            raise ValueError(f"lookahead k={k} is more than the re-ranker's {reranked.k} candidates")
        self.policy, self.k, self.reranked = policy, k, reranked

    def _dist(self, td: TensorDict) -> GridCategorical:
        with torch.no_grad():
            obs = td.select("observation", *FREE_ORDER_KEYS, strict=False).clone()
            dist = self.policy.get_dist(obs.to(policy_device(self.policy)))
        if not isinstance(dist, GridCategorical):
            raise ValueError("lookahead needs a spatial policy (one score per grid action)")
        return dist

    def _candidates(self, env: TangramEnv, td: TensorDict) -> torch.Tensor:
        """(N, k, 3) the k best grid actions in the policy's (or the re-ranker's) order, best first
        ((N, k, 4) with free order; on a refined grid each coarse cell with its most probable
        offset)."""
        if self.reranked is not None:
            return self.reranked.ranked(env, td)[:, : self.k].cpu()
        return self._dist(td).top_actions(self.k).cpu()

    def _greedy(self, env: TangramEnv, td: TensorDict) -> torch.Tensor:
        return self.reranked(env, td).cpu() if self.reranked is not None else self._dist(td).mode.cpu()

    def plan(self, env: TangramEnv, targets: np.ndarray, mirrored: np.ndarray | None = None) -> np.ndarray:
        """The chosen (x, y, orientation) index of every step of every target: (n, pieces, 3);
        with free order (piece, x, y, orientation), on a refined grid (x, y, orientation, fine):
        (n, pieces, 4)."""
        return self._run(env, targets, mirrored)[0]

    def label(
        self,
        env: TangramEnv,
        targets: np.ndarray,
        mirrored: np.ndarray | None = None,
        on_state: Callable[[TangramEnv, np.ndarray], torch.Tensor | dict[str, torch.Tensor]] | None = None,
    ) -> tuple[PlannerLabels, np.ndarray]:
        """Plan ``targets`` and keep, for every step, the state, the k candidates and their
        completions' IoUs; also the plan (as :meth:`plan`). ``on_state(env, rows)`` is called at
        each planned state (k copies of each target stand in it) with the worlds of the targets'
        first copies, and what it returns for them (one row each, or a dict of such) is kept as
        ``extra``."""
        chosen, labels = self._run(env, targets, mirrored, record=True, on_state=on_state)
        assert labels is not None
        return labels, chosen

    def _run(
        self,
        env: TangramEnv,
        targets: np.ndarray,
        mirrored: np.ndarray | None,
        record: bool = False,
        on_state: Callable[[TangramEnv, np.ndarray], torch.Tensor | dict[str, torch.Tensor]] | None = None,
    ) -> tuple[np.ndarray, PlannerLabels | None]:
        n, nw, p, k = len(targets), env.batch_size[0], env.num_pieces, self.k
        if nw < k:
            raise ValueError(f"lookahead k={k} needs at least k worlds, the env has {nw}")
        per = nw // k
        inputs = ["observation", *(FREE_ORDER_KEYS if env.free_order else ())]
        chosen = np.zeros((n, p, env.action_spec.shape[-1]), dtype=np.int64)
        rec: dict[str, list] = {
            "observation": [],
            "candidates": [],
            "iou": [],
            "step": [],
            "extra": [],
            "remaining": [],
        }
        for start in range(0, n, per):
            m = min(per, n - start)
            # World i * k + c tries candidate c for target i; the rest repeat the last copy.
            rows = np.minimum(np.arange(nw) // k, m - 1) + start
            first = torch.arange(m) * k  # each target's first copy
            faces = None if mirrored is None else mirrored[rows]
            cand = torch.arange(nw) % k
            for t in range(p):
                td = env.reset_to(targets[rows], faces)
                for s in range(p):
                    if s < t:
                        action = torch.as_tensor(chosen[rows, s])
                    elif s == t:
                        # Every copy of a target sees the same state, so the same top k; the
                        # policy's own order (its mode first), so that k = 1 is the greedy policy.
                        top = self._candidates(env, td)
                        action = top[torch.arange(nw), cand]
                        tried = action
                        if record:
                            rec["observation"].append(td["observation"][first].clone())
                            rec["candidates"].append(top[first])
                            rec["step"].append(torch.full((m,), t, dtype=torch.int64))
                            if env.free_order:
                                rec["remaining"].append(td["remaining"][first].cpu().clone())
                            if on_state is not None:
                                rec["extra"].append(on_state(env, first.numpy()))
                    else:
                        action = self._greedy(env, td)
                    nxt = env.step(td.set("action", action.to(env.device)))["next"]
                    td = nxt.select(*inputs)
                iou = nxt["info", "iou"][: m * k, 0].reshape(m, k).cpu()
                best = iou.argmax(1)  # the first of equal IoUs: the policy's order
                picks = first + best
                chosen[start : start + m, t] = tried[picks].numpy()
                if record:
                    rec["iou"].append(iou.float())
        if not record:
            return chosen, None
        # Rows in (chunk, step, target) order; each tensor's rows line up.
        cat = {key: torch.cat(v) for key, v in rec.items() if v and key != "extra"}
        return chosen, PlannerLabels(
            observation=cat["observation"],
            candidates=cat["candidates"],
            iou=cat["iou"],
            step=cat["step"],
            extra=_cat(rec["extra"]) if rec["extra"] else None,
            remaining=cat.get("remaining"),
        )

    def actor(self, env: TangramEnv, targets: np.ndarray, mirrored: np.ndarray | None = None) -> Actor:
        """An actor that plays the planned episodes of ``targets`` through
        :func:`mrchaos.learn.evaluate.evaluate` (which takes them in chunks of the env's worlds)."""
        return self.replay(self.plan(env, targets, mirrored), env)

    @staticmethod
    def replay(chosen: np.ndarray, env: TangramEnv) -> Actor:
        """An actor that plays a plan (n, pieces, 3 or 4) through
        :func:`mrchaos.learn.evaluate.evaluate` on ``env``."""
        n, nw, p = len(chosen), env.batch_size[0], env.num_pieces
        calls = itertools.count()  # evaluate asks step by step, chunk by chunk

        def act(e: TangramEnv, td: TensorDict) -> torch.Tensor:
            c = next(calls)
            start, t = (c // p) * nw, c % p
            rows = np.minimum(np.arange(start, start + nw), n - 1)
            return torch.as_tensor(chosen[rows, t]).to(e.device)

        return act
