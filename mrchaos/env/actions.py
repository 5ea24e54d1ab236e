"""The discrete action grid: placement poses (x, y, theta) as indices.

The reference code's ``MultiDiscrete([51, 51, 8])``: x and y from -0.10 to +0.10 m
in 4 mm steps, theta from -180 deg to +135 deg in 45 deg steps.

With ``flip`` the third index also chooses the face of a chiral piece: indices
``0..ntheta-1`` place it face up, ``ntheta..2*ntheta-1`` turned over (its mirror image),
so the spatial policy's head gets a second set of orientation channels and the action
stays three indices. Pieces that are not chiral ignore the face: turned over, they are
the same set of poses.

**Precision past the grid** (``fine_xy``, ``fine_theta``): a fourth index picks an offset inside
the coarse cell, ``fine_xy`` positions per axis across one x/y step and ``fine_theta`` angles
across one angle step, centred on the coarse pose. Both are odd, so the middle offset is the
coarse pose itself and the refined poses are a superset of the coarse ones: a coarse-to-fine
action reaches what a grid ``fine_xy`` times finer reaches, with ``nx * ny * norient`` coarse
choices plus ``fine_xy**2 * fine_theta`` fine ones instead of their product.
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
        fine_xy, fine_theta: offsets inside a coarse cell per position axis and per angle step
            (odd; 1 and 1: no fourth index; see the module docstring).
    """

    nx: int = 51
    ny: int = 51
    ntheta: int = 8
    half_range: float = 0.10
    theta_min: float = -math.pi
    flip: bool = False
    fine_xy: int = 1
    fine_theta: int = 1

    def __post_init__(self) -> None:
        if min(self.nx, self.ny, self.ntheta) < 1:
            raise ValueError(f"action grid sizes must be >= 1, got {self.nvec}")
        for key in ("fine_xy", "fine_theta"):
            v = getattr(self, key)
            if v < 1 or v % 2 == 0:
                raise ValueError(f"env.grid.{key} must be odd and >= 1 (its middle offset is the coarse pose), got {v}")
        if self.fine_xy > 1 and min(self.nx, self.ny) < 2:
            raise ValueError(f"env.grid.fine_xy needs at least 2 cells per axis to know the step, got {self.nvec}")

    @property
    def nfine(self) -> int:
        """Offsets inside a coarse cell (1: the grid is not refined)."""
        return self.fine_xy**2 * self.fine_theta

    @property
    def refined(self) -> bool:
        """Whether the action carries a fourth, fine index."""
        return self.nfine > 1

    @property
    def faces(self) -> int:
        """Faces a piece may be placed on: 2 with ``flip``, else 1."""
        return 2 if self.flip else 1

    @property
    def norient(self) -> int:
        """Size of the third action index: angles times faces."""
        return self.ntheta * self.faces

    @property
    def nvec(self) -> tuple[int, ...]:
        """Size of each action index: (nx, ny, norient), and nfine when refined."""
        return (self.nx, self.ny, self.norient) + ((self.nfine,) if self.refined else ())

    @property
    def size(self) -> int:
        """Distinct actions: coarse cells times fine offsets."""
        return self.nx * self.ny * self.norient * self.nfine

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

    def _steps(self) -> tuple[float, float, float]:
        """The coarse x, y and angle steps."""
        dx = 2 * self.half_range / (self.nx - 1) if self.nx > 1 else 0.0
        dy = 2 * self.half_range / (self.ny - 1) if self.ny > 1 else 0.0
        return dx, dy, 2 * math.pi / self.ntheta

    def fine_offsets(self, fine: np.ndarray) -> np.ndarray:
        """(...,) fine indices -> (..., 3) offsets (m, m, rad) from the coarse pose."""
        f = np.asarray(fine, dtype=np.int64)
        r, q = self.fine_xy, self.fine_theta
        dx, dy, dt = self._steps()
        fx, fy, ft = f % r, (f // r) % r, f // (r * r)
        h, ht = (r - 1) / 2, (q - 1) / 2
        return np.stack([(fx - h) * dx / r, (fy - h) * dy / r, (ft - ht) * dt / q], axis=-1)

    def to_pose(self, action: np.ndarray) -> np.ndarray:
        """(..., 3) integer indices, (..., 4) on a refined grid -> (..., 3) poses (m, m, rad)."""
        a = np.asarray(action)
        pose = np.stack([self.xs[a[..., 0]], self.ys[a[..., 1]], self.thetas[a[..., 2] % self.ntheta]], axis=-1)
        if self.refined:
            pose = pose + self.fine_offsets(a[..., 3])
        return pose

    def mirrored(self, action: np.ndarray) -> np.ndarray:
        """(..., 3) integer indices -> (...,) bool: the piece goes down turned over, as its mirror
        image (always False without flip)."""
        return np.asarray(action)[..., 2] >= self.ntheta

    def nearest(
        self, pose: np.ndarray, period: np.ndarray | float = 2 * math.pi, mirrored: np.ndarray | None = None
    ) -> np.ndarray:
        """(..., 3) poses -> nearest (..., 3) indices, (..., 4) on a refined grid; theta is matched
        modulo the piece's symmetry period.

        ``mirrored`` (...,) bool picks the turned-over face's indices (needs ``flip``)."""
        pose = np.asarray(pose, dtype=np.float64)
        r, q = self.fine_xy, self.fine_theta
        # Every reachable value per axis, coarse-major: value k is coarse k // r, offset k % r.
        xs = (self.xs[:, None] + self.fine_offsets(np.arange(r))[None, :, 0]).ravel()
        ys = (self.ys[:, None] + self.fine_offsets(np.arange(r) * r)[None, :, 1]).ravel()
        ts = (self.thetas[:, None] + self.fine_offsets(np.arange(q) * r * r)[None, :, 2]).ravel()
        kx = np.abs(pose[..., 0, None] - xs).argmin(-1)
        ky = np.abs(pose[..., 1, None] - ys).argmin(-1)
        kt = angle_gap(pose[..., 2, None], ts, np.asarray(period)[..., None]).argmin(-1)
        it = kt // q
        if mirrored is not None and np.any(mirrored):
            if not self.flip:
                raise ValueError("a turned-over piece needs an action grid with flip (env.grid.flip: true)")
            it = it + self.ntheta * np.asarray(mirrored, dtype=np.int64)
        index = [kx // r, ky // r, it]
        if self.refined:
            index.append(kx % r + r * (ky % r) + r * r * (kt % q))
        return np.stack(index, axis=-1).astype(np.int64)
