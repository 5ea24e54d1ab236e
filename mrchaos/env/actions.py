"""The discrete action grid: placement poses (x, y, theta) as indices.

The reference code's ``MultiDiscrete([51, 51, 8])``: x and y from -0.10 to +0.10 m
in 4 mm steps, theta from -180 deg to +135 deg in 45 deg steps.

With ``flip`` the third index also chooses the face of a chiral piece: indices
``0..ntheta-1`` place it face up, ``ntheta..2*ntheta-1`` turned over (its mirror image),
so the spatial policy's head gets a second set of orientation channels and the action
stays three indices. Pieces that are not chiral ignore the face: turned over, they are
the same set of poses.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mrchaos.core.geometry import angle_gap

__all__ = ["ActionGrid"]


@dataclass(frozen=True)
class ActionGrid:
    """A regular grid of placement poses.

    Attributes:
        nx, ny, ntheta: number of bins per dimension.
        half_range: x and y span [-half_range, +half_range] (m).
        theta_min: first angle (rad); angles step by 2*pi/ntheta.
        flip: the third index also chooses the face (see the module docstring).
    """

    nx: int = 51
    ny: int = 51
    ntheta: int = 8
    half_range: float = 0.10
    theta_min: float = -math.pi
    flip: bool = False

    def __post_init__(self) -> None:
        if min(self.nx, self.ny, self.ntheta) < 1:
            raise ValueError(f"action grid sizes must be >= 1, got {self.nvec}")

    @property
    def faces(self) -> int:
        """Faces a piece may be placed on: 2 with ``flip``, else 1."""
        return 2 if self.flip else 1

    @property
    def norient(self) -> int:
        """Size of the third action index: angles times faces."""
        return self.ntheta * self.faces

    @property
    def nvec(self) -> tuple[int, int, int]:
        return (self.nx, self.ny, self.norient)

    @property
    def size(self) -> int:
        return self.nx * self.ny * self.norient

    def _axis(self, n: int) -> np.ndarray:
        return np.linspace(-self.half_range, self.half_range, n) if n > 1 else np.zeros(1)

    @property
    def xs(self) -> np.ndarray:
        return self._axis(self.nx)

    @property
    def ys(self) -> np.ndarray:
        return self._axis(self.ny)

    @property
    def thetas(self) -> np.ndarray:
        return self.theta_min + np.arange(self.ntheta) * (2 * math.pi / self.ntheta)

    def to_pose(self, action: np.ndarray) -> np.ndarray:
        """(..., 3) integer indices -> (..., 3) poses (m, m, rad)."""
        a = np.asarray(action)
        return np.stack([self.xs[a[..., 0]], self.ys[a[..., 1]], self.thetas[a[..., 2] % self.ntheta]], axis=-1)

    def mirrored(self, action: np.ndarray) -> np.ndarray:
        """(..., 3) integer indices -> (...,) bool: the piece goes down turned over, as its mirror
        image (always False without flip)."""
        return np.asarray(action)[..., 2] >= self.ntheta

    def nearest(
        self, pose: np.ndarray, period: np.ndarray | float = 2 * math.pi, mirrored: np.ndarray | None = None
    ) -> np.ndarray:
        """(..., 3) poses -> nearest (..., 3) indices; theta is matched modulo the piece's symmetry period.

        ``mirrored`` (...,) bool picks the turned-over face's indices (needs ``flip``)."""
        pose = np.asarray(pose, dtype=np.float64)
        ix = np.abs(pose[..., 0, None] - self.xs).argmin(-1)
        iy = np.abs(pose[..., 1, None] - self.ys).argmin(-1)
        gap = angle_gap(pose[..., 2, None], self.thetas, np.asarray(period)[..., None])
        it = gap.argmin(-1)
        if mirrored is not None and np.any(mirrored):
            if not self.flip:
                raise ValueError("a turned-over piece needs an action grid with flip (env.grid.flip: true)")
            it = it + self.ntheta * np.asarray(mirrored, dtype=np.int64)
        return np.stack([ix, iy, it], axis=-1).astype(np.int64)
