"""Counterfactual coverage: what placing the next piece would earn, for every grid action at once.

A placement whose footprint touches nothing earns the coverage of the piece's slot,
|F ∩ S| / |S| (twins: the better slot). For all (x, y, theta) at once that is a
cross-correlation of the slot mask S with the piece's footprint F rotated to theta, read
at the grid's positions. It is computed on a raster finer than the camera's, whose pixel
is a whole fraction of the grid step so that every grid point is a pixel centre (for the
tangram, 2 mm pixels and 4 mm steps), as one strided convolution per piece.

With a flip grid (``ActionGrid.flip``) the orientation index also chooses the face: the
second ``ntheta`` kernels are the chiral pieces' mirror images (a piece that is not chiral
goes down as itself, as the env places it), and the slots are rasterised with the targets'
own faces, so that a turned-over slot is covered by the turned-over actions.

Footprints that overlap pieces already placed are where physics decides the outcome (the
piece lands on top, tilts, or pushes); :func:`CounterfactualGrid.coverage` reports the
overlapping share of the footprint beside the coverage, so that callers mask or penalise
those actions. The env serves this as a privileged answer (``TangramEnv.counterfactual``),
like its oracle: policies never see it, supervision does.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from mrchaos.core.geometry import rigid_transform
from mrchaos.core.raster import View, rasterize
from mrchaos.env.actions import ActionGrid
from mrchaos.figures.pieces import PieceSet

__all__ = ["CounterfactualGrid"]


class CounterfactualGrid:
    """Kernels and the fine raster for one piece set and action grid.

    Args:
        piece_set: the pieces.
        grid: the action grid (x and y steps must be equal).
        subdiv: fine pixels per grid step (2: 2 mm pixels for the tangram's 4 mm steps).
    """

    def __init__(self, piece_set: PieceSet, grid: ActionGrid, subdiv: int = 2) -> None:
        if grid.nx != grid.ny or grid.nx < 2:
            raise ValueError(f"counterfactual coverage needs equal x and y steps (nx = ny >= 2), got {grid.nvec}")
        self.piece_set, self.grid, self.subdiv = piece_set, grid, subdiv
        step = 2 * grid.half_range / (grid.nx - 1)
        px = step / subdiv
        radius = float(np.abs(piece_set.padded_parts()).max()) + float(np.abs(piece_set.action_origins()).max())
        self.k = 2 * math.ceil(radius / px) + 1  # kernel side (odd: the action origin at its centre pixel)
        # A view whose pixel centres hit every grid point and that holds every kernel placed on the grid.
        half = (grid.nx - 1) // 2 * subdiv + self.k // 2
        size = 2 * half + 1
        # Grid x0 (and the top row's y) then sits at pixel k // 2, so a stride-subdiv
        # convolution with no padding puts output o on grid point o.
        self.view = View(extent=size * px, size=size)
        self.kernels = self._kernels(px)  # (P, T, 1, k, k) float32, T = grid.norient
        self.kernel_area = self.kernels.flatten(2).sum(-1)  # (P, T)

    def _kernels(self, px: float) -> torch.Tensor:
        ps, g = self.piece_set, self.grid
        kview = View(extent=self.k * px, size=self.k)
        out = torch.zeros(len(ps), g.norient, 1, self.k, self.k)
        kk = ps.parts_per_piece
        origin = np.zeros((g.ntheta, 3))
        origin[:, 2] = g.thetas
        for face in range(g.faces):
            # Turned over, only a chiral piece changes shape (the env places the others face up).
            mirrored = ps.chiral if face else np.zeros(len(ps), dtype=bool)
            parts = ps.padded_parts(mirrored)
            for i in range(len(ps)):
                centroid = ps.to_centroid(np.full(g.ntheta, i), origin, np.full(g.ntheta, mirrored[i]))  # (T, 3)
                polys = rigid_transform(parts[i * kk : (i + 1) * kk][None], centroid[:, None])  # (T, K, V, 2)
                out[i, face * g.ntheta : (face + 1) * g.ntheta, 0] = (rasterize(polys, kview).ids >= 0).float()
        return out

    def _correlate(self, masks: torch.Tensor, piece: torch.Tensor) -> torch.Tensor:
        """(N, T, Y, X) sums of each mask (N, H, W) under piece[i]'s footprint at every grid action."""
        n = masks.shape[0]
        g = self.grid
        out = torch.zeros(n, g.norient, g.ny, g.nx)
        x = masks.float()[:, None]
        for i in torch.unique(piece).tolist():
            rows = (piece == i).nonzero()[:, 0]
            res = F.conv2d(x[rows], self.kernels[i], stride=self.subdiv)  # (m, T, ny, nx), image rows down
            out[rows] = res[..., : g.ny, : g.nx].flip(-2)  # grid y index ascends upwards
        return out

    def coverage(
        self,
        piece: np.ndarray,
        targets: np.ndarray,
        placed_polys: np.ndarray,
        placed: np.ndarray,
        twins: np.ndarray,
        mirrored: np.ndarray | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Counterfactual coverage and overlap of every grid action, (N, T, Y, X) each, in [0, 1]
        (T = ``grid.norient``: face-up orientations, then turned-over ones with a flip grid).

        Args:
            piece: (N,) the piece each world places next.
            targets: (N, P, 3) target centroid poses.
            placed_polys: (N, P*K, V, 2) current footprints of the pieces' parts.
            placed: (N, P) which pieces are on the table.
            twins: (P, P) bool, pieces that may fill each other's slot.
            mirrored: (N, P) bool, target pieces that lie turned over (default: none).
        """
        ps = self.piece_set
        parts = ps.raster_parts
        slot_ids = rasterize(ps.footprints(targets, mirrored), self.view, parts=parts).ids  # (N, H, W)
        occ = rasterize(placed_polys, self.view, visible=placed, parts=parts).ids >= 0
        piece_t = torch.as_tensor(piece, dtype=torch.long)
        best = torch.zeros(len(piece), self.grid.norient, self.grid.ny, self.grid.nx)
        for j in range(len(ps)):
            # Slot j counts for the worlds whose next piece may fill it.
            rows = np.flatnonzero(twins[np.asarray(piece), j])
            if len(rows) == 0:
                continue
            mask = slot_ids[rows] == j
            area = mask.flatten(1).sum(1).clamp(min=1).float()[:, None, None, None]
            cov = self._correlate(mask, piece_t[rows]) / area
            best[rows] = torch.maximum(best[rows], cov)
        overlap = self._correlate(occ, piece_t) / self.kernel_area[piece_t][:, :, None, None]
        return best.clamp(0.0, 1.0), overlap.clamp(0.0, 1.0)
