"""The scripted oracle: places every piece at its true target pose.

It reads the solution (the target poses), which a learnt policy never sees, so
it measures ceilings, not skill: ``exact`` is the placement pipeline's ceiling and
``grid`` (the nearest action of the grid) the action grid's ceiling.

With free order (``env.order: free``) the oracle places the pieces it is given, one per world
(:func:`random_pieces` draws them among the allowed ones), and a grid action carries the piece
first: (piece, x, y, theta).
"""

from __future__ import annotations

import numpy as np
import torch

from mrchaos.env.tangram import TangramEnv

__all__ = ["oracle_poses", "oracle_actions", "random_pieces"]


def oracle_poses(env: TangramEnv, piece: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) exact target pose of each world's next piece (its own slot; ``piece`` (N,) with free
    order), and (N,) whether it lies turned over."""
    answer = env.oracle_targets(piece)
    return answer.pose, answer.mirrored


def oracle_actions(env: TangramEnv, piece: np.ndarray | None = None) -> torch.Tensor:
    """(N, 3) grid action nearest to each world's next target pose (theta modulo the piece's symmetry,
    on the turned-over face where the target lies so); with free order (N, 4), ``piece`` (N,) first."""
    answer = env.oracle_targets(piece)
    period = np.array([p.symmetry_period for p in env.piece_set.pieces])[answer.piece]
    origin = env.piece_set.to_origin(answer.piece, answer.pose, answer.mirrored)
    grid = env.grid.nearest(origin, period, answer.mirrored)
    if env.free_order:
        grid = np.concatenate([answer.piece[:, None], grid], 1)
    return torch.as_tensor(grid)


def random_pieces(env: TangramEnv, generator: torch.Generator) -> np.ndarray:
    """(N,) a piece drawn uniformly among each world's allowed ones (:meth:`TangramEnv.choosable`;
    piece 0 in a finished world, which places nothing)."""
    ok = torch.as_tensor(env.choosable())
    weights = torch.where(ok.any(1, keepdim=True), ok.float(), torch.ones_like(ok, dtype=torch.float32))
    return torch.multinomial(weights, 1, generator=generator)[:, 0].numpy()
