"""Test-time lookahead: each placement chosen among a policy's top-k actions by where greedy
completions in the simulator end, scored on the silhouette alone (no solution is read).

For every step t of an episode, k copies of the world replay the placements chosen so far, each
copy places the piece at one of the policy's k best actions (``GridCategorical.top_modes``: with a
mode window, k separate peaks), and the policy then
completes the assembly greedily. The candidate whose completion reaches the highest IoU of the
occupied area with the silhouette wins (ties go to the policy's order, so k = 1 is the greedy
policy). IoU is observable: the silhouette is the prompt and the occupied area is the view. The
planner uses the simulator as its model, so it is a planner around the policy, not the policy alone,
and the bench labels it so. The cost is about k × pieces² env steps per episode instead of pieces.
"""

from __future__ import annotations

import itertools

import numpy as np
import torch
from tensordict import TensorDict

from mrchaos.env.tangram import TangramEnv
from mrchaos.learn.evaluate import Actor
from mrchaos.learn.policy import GridCategorical, unravel_actions

__all__ = ["Lookahead"]


class Lookahead:
    """Plans whole episodes for a spatial policy (a ``GridCategorical`` over the grid's actions)."""

    def __init__(self, policy, k: int) -> None:
        if k < 1:
            raise ValueError(f"lookahead k must be >= 1, got {k}")
        self.policy, self.k = policy, k

    def _dist(self, td: TensorDict) -> GridCategorical:
        with torch.no_grad():
            dist = self.policy.get_dist(td.select("observation").clone())
        if not isinstance(dist, GridCategorical):
            raise ValueError("lookahead needs a spatial policy (one score per grid action)")
        return dist

    def plan(self, env: TangramEnv, targets: np.ndarray, mirrored: np.ndarray | None = None) -> np.ndarray:
        """The chosen (x, y, orientation) index of every step of every target: (n, pieces, 3)."""
        n, nw, p, k = len(targets), env.batch_size[0], env.num_pieces, self.k
        if nw < k:
            raise ValueError(f"lookahead k={k} needs at least k worlds, the env has {nw}")
        per = nw // k
        nx, ny, _ = env.grid.nvec
        chosen = np.zeros((n, p, 3), dtype=np.int64)
        for start in range(0, n, per):
            m = min(per, n - start)
            # World i * k + c tries candidate c for target i; the rest repeat the last copy.
            rows = np.minimum(np.arange(nw) // k, m - 1) + start
            faces = None if mirrored is None else mirrored[rows]
            cand = torch.arange(nw) % k
            for t in range(p):
                td = env.reset_to(targets[rows], faces)
                for s in range(p):
                    if s < t:
                        action = torch.as_tensor(chosen[rows, s])
                    else:
                        dist = self._dist(td)
                        if s == t:
                            # Every copy of a target sees the same state, so the same top k; the
                            # policy's own order (its mode first), so that k = 1 is the greedy policy.
                            top = dist.top_modes(k)
                            action = unravel_actions(top.gather(1, cand[:, None]).squeeze(1), nx, ny)
                            tried = action
                        else:
                            action = dist.mode
                    nxt = env.step(td.set("action", action.to(env.device)))["next"]
                    td = TensorDict(observation=nxt["observation"], batch_size=env.batch_size)
                iou = nxt["info", "iou"][: m * k, 0].reshape(m, k)
                best = iou.argmax(1)  # the first of equal IoUs: the policy's order
                picks = torch.arange(m) * k + best
                chosen[start : start + m, t] = tried[picks].numpy()
        return chosen

    def actor(self, env: TangramEnv, targets: np.ndarray, mirrored: np.ndarray | None = None) -> Actor:
        """An actor that plays the planned episodes of ``targets`` through
        :func:`mrchaos.learn.evaluate.evaluate` (which takes them in chunks of the env's worlds)."""
        chosen = self.plan(env, targets, mirrored)
        n, nw, p = len(targets), env.batch_size[0], env.num_pieces
        calls = itertools.count()  # evaluate asks step by step, chunk by chunk

        def act(e: TangramEnv, td: TensorDict) -> torch.Tensor:
            c = next(calls)
            start, t = (c // p) * nw, c % p
            rows = np.minimum(np.arange(start, start + nw), n - 1)
            return torch.as_tensor(chosen[rows, t]).to(e.device)

        return act
