"""The scripted oracle: places every piece at its true target pose.

It reads the solution (the target poses), which a learnt policy never sees, so
it measures ceilings, not skill: ``exact`` is the placement pipeline's ceiling and
``grid`` (the nearest action of the grid) the action grid's ceiling.
"""

from __future__ import annotations

import numpy as np
import torch

from mrchaos.env.tangram import TangramEnv

__all__ = ["oracle_poses", "oracle_actions"]


def oracle_poses(env: TangramEnv) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) exact target pose of each world's next piece (its own slot), and (N,) whether it lies turned over."""
    answer = env.oracle_targets()
    return answer.pose, answer.mirrored


def oracle_actions(env: TangramEnv) -> torch.Tensor:
    """(N, 3) grid action nearest to each world's next target pose (theta modulo the piece's symmetry,
    on the turned-over face where the target lies so)."""
    answer = env.oracle_targets()
    period = np.array([p.symmetry_period for p in env.piece_set.pieces])[answer.piece]
    origin = env.piece_set.to_origin(answer.piece, answer.pose, answer.mirrored)
    return torch.as_tensor(env.grid.nearest(origin, period, answer.mirrored))
