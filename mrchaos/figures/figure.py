"""Figures: a piece set plus one planar pose per piece, and their validation.

A figure is the target of an assembly episode. Human-designed figures come from
files (:mod:`mrchaos.figures.formats`, :mod:`mrchaos.figures.kilogram`) or the built-in library
(:mod:`mrchaos.figures.library`); random ("chaos") figures from :mod:`mrchaos.tasks.chaos`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from mrchaos.core.errors import MrchaosError
from mrchaos.core.geometry import (
    convex_penetration,
    fit_pose,
    polygon_area,
    rigid_transform,
)
from mrchaos.core.raster import View, rasterize
from mrchaos.figures.pieces import PieceSet

__all__ = ["Figure", "FigureError", "FigureSet", "figure_from_polygons", "mirror_figure", "FAMILIES"]

#: Evaluation families in the order the paper's Table I lists them.
FAMILIES = ("Random", "H-Normal", "H-Hard", "H-Fiendish")


class FigureError(MrchaosError, ValueError):
    """A figure or figure file is invalid; the message names the file and the figure."""


@dataclass
class Figure:
    """A target assembly.

    Attributes:
        id: identifier, unique within its set.
        piece_set: the pieces, in placement order.
        poses: (P, 3) float64, centroid x, y (m) and rotation theta (rad) of each piece.
        mirrored: (P,) bool, the piece appears as its mirror image. A suction robot
            cannot flip a piece, so such a figure cannot be assembled exactly.
        name: human-readable name.
        family: a family label given by the figure's set, or None to use the rule.
        source: where it came from (file path), for error messages.
        meta: provenance from importers (e.g. fit errors); not used by the maths.
    """

    id: str
    piece_set: PieceSet
    poses: np.ndarray
    mirrored: np.ndarray = field(default=None)  # type: ignore[arg-type]  # filled in __post_init__
    name: str = ""
    family: str | None = None
    source: str = ""
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.poses = np.asarray(self.poses, dtype=np.float64).reshape(-1, 3)
        if self.mirrored is None:
            self.mirrored = np.zeros(len(self.poses), dtype=bool)
        self.mirrored = np.asarray(self.mirrored, dtype=bool).reshape(-1)
        if not self.name:
            self.name = self.id

    @property
    def where(self) -> str:
        """'file: figure id' prefix for messages."""
        return f"{self.source or '<memory>'}: figure {self.id!r}"

    @property
    def has_mirrored(self) -> bool:
        """True when some chiral piece must be flipped, which a suction robot cannot do."""
        return bool(self.mirrored.any())

    def polygons(self) -> np.ndarray:
        """(P, Vmax, 2) world vertices of every piece, counter-clockwise (padded)."""
        return rigid_transform(self.piece_set.padded_outlines(self.mirrored), self.poses)

    def piece_polygon(self, i: int) -> np.ndarray:
        """(V, 2) world vertices of piece i, without padding."""
        p = self.piece_set.pieces[i]
        outline = p.mirrored_outline() if self.mirrored[i] else p.outline
        return rigid_transform(outline, self.poses[i])

    def target_ids(self, view: View = View()) -> torch.Tensor:
        """(H, W) int8 image of the target piece ids (-1 outside the silhouette)."""
        ps = self.piece_set
        return rasterize(ps.footprints(self.poses, self.mirrored)[None], view, parts=ps.raster_parts).ids[0]

    def silhouette(self, view: View = View()) -> torch.Tensor:
        """(H, W) bool silhouette image I_s."""
        return self.target_ids(view) >= 0

    def target_masks(self, view: View = View()) -> torch.Tensor:
        """(P, H, W) bool mask of each piece's target pixels."""
        ids = self.target_ids(view)
        return ids[None] == torch.arange(len(self.piece_set), dtype=torch.int8)[:, None, None]

    def overlap_area(self) -> float:
        """Total pairwise overlap area of the pieces (m^2), exact via shapely."""
        import shapely

        polys = [shapely.Polygon(self.piece_polygon(i)) for i in range(len(self.piece_set))]
        total = 0.0
        for i in range(len(polys)):
            for j in range(i + 1, len(polys)):
                total += polys[i].intersection(polys[j]).area
        return total

    def validate(self, view: View = View(), overlap_tol: float = 2.0e-4, outside_tol: float = 0.05) -> None:
        """Raise :class:`FigureError` naming the file and figure if the figure is unusable.

        Checks: one finite pose per piece; pieces do not overlap by more than
        ``overlap_tol`` m^2 in total (hand-digitised figures overlap a little at
        shared edges); no piece has more than ``outside_tol`` of its area outside
        the camera view.
        """
        n = len(self.piece_set)
        if self.poses.shape != (n, 3):
            raise FigureError(f"{self.where}: expected {n} piece poses, got {self.poses.shape[0]}")
        if self.mirrored.shape != (n,):
            raise FigureError(f"{self.where}: mirrored flags must have {n} entries")
        if not np.isfinite(self.poses).all():
            raise FigureError(f"{self.where}: pose contains NaN or inf")
        for i, p in enumerate(self.piece_set.pieces):
            if self.mirrored[i] and not p.chiral:
                self.mirrored[i] = False  # the mirror of an achiral piece is the piece itself
        polys = self.polygons()
        ia, ib = np.triu_indices(n, 1)
        depth = convex_penetration(polys[ia], polys[ib])
        if (depth > 1e-4).any():
            overlap = self.overlap_area()
            if overlap > overlap_tol:
                worst = int(np.argmax(depth))
                raise FigureError(
                    f"{self.where}: pieces overlap by {overlap * 1e6:.0f} mm^2 in total (tolerance "
                    f"{overlap_tol * 1e6:.0f} mm^2), worst pair {self.piece_set.names[ia[worst]]} / "
                    f"{self.piece_set.names[ib[worst]]}"
                )
        half = view.extent / 2
        for i in range(n):
            poly = self.piece_polygon(i)
            if np.abs(poly).max() <= half:
                continue
            import shapely

            sp = shapely.Polygon(poly)
            inside = sp.intersection(shapely.box(-half, -half, half, half)).area
            if inside < (1 - outside_tol) * sp.area:
                raise FigureError(
                    f"{self.where}: piece {self.piece_set.names[i]} lies {100 * (1 - inside / sp.area):.0f}% "
                    f"outside the {view.extent:.3f} m camera view"
                )


def mirror_figure(fig: Figure, suffix: str = "-mirrored") -> Figure:
    """The figure reflected in the y axis (x -> -x): every chiral piece changes face, so a figure
    built face up needs the chiral pieces turned over, and the other way round."""
    polys = [fig.piece_polygon(i) * np.array([-1.0, 1.0]) for i in range(len(fig.piece_set))]
    return figure_from_polygons(
        fig.piece_set, polys, fig.id + suffix, name=fig.name + suffix, family=fig.family, source=fig.source
    )


def figure_from_polygons(
    piece_set: PieceSet,
    polygons: list[np.ndarray],
    fig_id: str,
    *,
    name: str = "",
    family: str | None = None,
    source: str = "",
    tol: float = 0.5e-3,
) -> Figure:
    """Build a figure from world-frame polygons given in piece-set order.

    Each polygon is matched to its piece's outline (any vertex order and
    winding; the mirror image for chiral pieces) and its pose recovered. A polygon
    whose best fit leaves an RMS vertex error above ``tol`` metres is not that piece.
    """
    where = f"{source or '<memory>'}: figure {fig_id!r}"
    if len(polygons) != len(piece_set):
        raise FigureError(f"{where}: expected {len(piece_set)} pieces, got {len(polygons)}")
    poses = np.zeros((len(piece_set), 3))
    mirrored = np.zeros(len(piece_set), dtype=bool)
    for i, (piece, poly) in enumerate(zip(piece_set.pieces, polygons, strict=True)):
        v = np.asarray(poly, dtype=np.float64)
        if v.ndim != 2 or v.shape[1] != 2:
            raise FigureError(f"{where}: piece {piece.name}: vertices must be a list of [x, y] pairs")
        if not np.isfinite(v).all():
            raise FigureError(f"{where}: piece {piece.name}: vertices contain NaN or inf")
        if len(v) != len(piece.outline):
            raise FigureError(f"{where}: piece {piece.name} needs {len(piece.outline)} vertices, got {len(v)}")
        if not math.isclose(abs(polygon_area(v)), piece.area, rel_tol=0.05):
            raise FigureError(
                f"{where}: piece {piece.name} has area {abs(polygon_area(v)) * 1e6:.0f} mm^2, "
                f"expected {piece.area * 1e6:.0f} mm^2"
            )
        fit = fit_pose(piece.outline, v, piece.mirrored_outline() if piece.chiral else None)
        if fit.residual > tol:
            raise FigureError(
                f"{where}: piece {piece.name} does not match its shape (RMS vertex error "
                f"{fit.residual * 1e3:.2f} mm > {tol * 1e3:.2f} mm)"
            )
        poses[i] = fit.pose
        mirrored[i] = fit.mirrored
    return Figure(fig_id, piece_set, poses, mirrored, name=name, family=family, source=source)


@dataclass
class FigureSet:
    """Figures loaded from one source, plus the ones that failed validation (never silently dropped)."""

    name: str
    figures: list[Figure]
    rejected: list[tuple[str, str]] = field(default_factory=list)  # (figure id, reason)
    source: str = ""
