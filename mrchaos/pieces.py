"""Piece sets: the rigid parts a figure is assembled from, as data.

A piece set is an ordered tuple of pieces. A piece's identity everywhere in the
package is its index in that order, which is also the placement order (largest
first for the tangram). Outlines are convex polygons in metres, counter-clockwise,
with their area centroid at the origin, so a pose (x, y, theta) places the
centroid at (x, y) and rotates the outline by theta about it.

New part sets (cutlery, soda cans, ...) plug in through :func:`register_piece_set`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from mrchaos.geometry import polygon_area, polygon_centroid

__all__ = [
    "Piece",
    "PieceSet",
    "tangram7",
    "register_piece_set",
    "get_piece_set",
    "piece_set_names",
]


@dataclass(frozen=True)
class Piece:
    """One rigid part.

    Attributes:
        name: unique name within its set.
        outline: (V, 2) convex polygon, metres, counter-clockwise, centroid at the origin.
        thickness: extrusion height in metres.
        symmetry: order of rotational symmetry (1 = none, 2 = 180 deg, 4 = 90 deg,
            0 = continuous, e.g. a disc).
        chiral: True when the mirror image is a different shape that a top-down
            suction gripper cannot produce (it cannot flip a part over).
        mass: kilograms; default from a plywood-like density.
        action_origin: the point (centroid frame, m) that a placement action positions.
            The reference code positions each tangram piece by its mesh origin, not its
            centroid; keeping that point makes the action grid's rounding identical.
    """

    name: str
    outline: np.ndarray
    thickness: float
    symmetry: int = 1
    chiral: bool = False
    mass: float | None = None
    action_origin: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        outline = np.asarray(self.outline, dtype=np.float64)
        if outline.ndim != 2 or outline.shape[1] != 2 or outline.shape[0] < 3:
            raise ValueError(f"piece {self.name!r}: outline must be (V>=3, 2), got {outline.shape}")
        if polygon_area(outline) < 0:
            outline = outline[::-1].copy()
        outline = outline - polygon_centroid(outline)
        outline.setflags(write=False)
        object.__setattr__(self, "outline", outline)
        if self.mass is None:
            object.__setattr__(self, "mass", 600.0 * self.area * self.thickness)

    @property
    def area(self) -> float:
        """Area of the outline in m^2."""
        return polygon_area(self.outline)

    @property
    def radius(self) -> float:
        """Largest distance from the centroid to a vertex (m)."""
        return float(np.linalg.norm(self.outline, axis=1).max())

    @property
    def symmetry_period(self) -> float:
        """Rotation (rad) that maps the piece onto itself; 0 for continuous symmetry."""
        return 0.0 if self.symmetry == 0 else 2 * math.pi / self.symmetry

    def mirrored_outline(self) -> np.ndarray:
        """Outline reflected about the y axis, still counter-clockwise and centred."""
        m = self.outline * np.array([-1.0, 1.0])
        return m[::-1].copy()


@dataclass(frozen=True)
class PieceSet:
    """An ordered set of pieces. Index in ``pieces`` is the piece id and the placement order.

    ``twins`` groups interchangeable pieces (same shape): a piece may fill any
    slot of its group when rewards are computed.
    """

    name: str
    pieces: tuple[Piece, ...]
    twins: tuple[tuple[int, ...], ...] = field(default=())

    def __post_init__(self) -> None:
        names = [p.name for p in self.pieces]
        if len(set(names)) != len(names):
            raise ValueError(f"piece set {self.name!r}: duplicate piece names {names}")
        seen: set[int] = set()
        for group in self.twins:
            for i in group:
                if not 0 <= i < len(self.pieces) or i in seen:
                    raise ValueError(f"piece set {self.name!r}: bad twin group {group}")
                seen.add(i)
            shapes = {self.pieces[i].outline.tobytes() for i in group}
            if len(shapes) != 1:
                raise ValueError(f"piece set {self.name!r}: twins {group} differ in shape")

    def __len__(self) -> int:
        return len(self.pieces)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.pieces)

    def index(self, name: str) -> int:
        """Piece id of a piece name."""
        try:
            return self.names.index(name)
        except ValueError:
            raise KeyError(f"piece set {self.name!r} has no piece {name!r}; pieces: {list(self.names)}") from None

    @property
    def total_area(self) -> float:
        return float(sum(p.area for p in self.pieces))

    def twin_group_of(self) -> np.ndarray:
        """(P,) int: for each piece, the id of the first piece of its twin group (itself if none)."""
        rep = np.arange(len(self.pieces))
        for group in self.twins:
            for i in group:
                rep[i] = min(group)
        return rep

    def twin_matrix(self) -> np.ndarray:
        """(P, P) bool: True where piece i may fill slot j (same piece or twins)."""
        rep = self.twin_group_of()
        return rep[:, None] == rep[None, :]

    def action_origins(self) -> np.ndarray:
        """(P, 2) action origin of every piece in its centroid frame."""
        return np.array([p.action_origin for p in self.pieces], dtype=np.float64)

    def to_centroid(self, piece: np.ndarray, pose: np.ndarray) -> np.ndarray:
        """Poses (..., 3) of action origins -> centroid poses of the given pieces."""
        return self._shift(piece, pose, -1.0)

    def to_origin(self, piece: np.ndarray, pose: np.ndarray) -> np.ndarray:
        """Centroid poses (..., 3) -> poses of the pieces' action origins."""
        return self._shift(piece, pose, 1.0)

    def _shift(self, piece: np.ndarray, pose: np.ndarray, sign: float) -> np.ndarray:
        pose = np.asarray(pose, dtype=np.float64)
        off = self.action_origins()[np.asarray(piece)]
        c, s = np.cos(pose[..., 2]), np.sin(pose[..., 2])
        out = pose.copy()
        out[..., 0] += sign * (c * off[..., 0] - s * off[..., 1])
        out[..., 1] += sign * (s * off[..., 0] + c * off[..., 1])
        return out

    @property
    def max_vertices(self) -> int:
        return max(len(p.outline) for p in self.pieces)

    def padded_outlines(self, mirrored: np.ndarray | None = None) -> np.ndarray:
        """(P, Vmax, 2) outlines; shorter polygons repeat their last vertex (a zero-length edge).

        ``mirrored`` (P,) bool selects the mirror image of chiral pieces.
        """
        vmax = self.max_vertices
        out = np.zeros((len(self.pieces), vmax, 2))
        for i, p in enumerate(self.pieces):
            o = p.mirrored_outline() if (mirrored is not None and mirrored[i]) else p.outline
            out[i, : len(o)] = o
            out[i, len(o) :] = o[-1]
        return out


def _tri(leg: float) -> np.ndarray:
    return np.array([[0.0, 0.0], [leg, 0.0], [0.0, leg]])


def tangram7() -> PieceSet:
    """The classic seven-piece tangram of a 100 mm square, 10 mm thick, largest first.

    The parallelogram's handedness (long edge at the bottom, leaning left) is the one
    the MRChaos evaluation figures use; its mirror image needs the piece flipped.
    """
    s = 0.1 / math.sqrt(2.0)  # 70.71 mm: large-triangle leg
    t = 0.010

    def tri_origin(leg: float) -> tuple[float, float]:
        # The reference meshes put a triangle's origin a quarter leg from the right-angle
        # corner along each leg; the centroid is a third of a leg from it.
        return (-leg / 12, -leg / 12)

    pieces = (
        Piece("large_triangle_1", _tri(s), t, action_origin=tri_origin(s)),
        Piece("large_triangle_2", _tri(s), t, action_origin=tri_origin(s)),
        Piece("square", np.array([[0, 0], [s / 2, 0], [s / 2, s / 2], [0, s / 2]]), t, symmetry=4),
        Piece(
            "parallelogram",
            np.array([[0.0, 0.0], [0.05, 0.0], [0.025, 0.025], [-0.025, 0.025]]),
            t,
            symmetry=2,
            chiral=True,
        ),
        Piece("medium_triangle", _tri(0.05), t, action_origin=tri_origin(0.05)),
        Piece("small_triangle_1", _tri(s / 2), t, action_origin=tri_origin(s / 2)),
        Piece("small_triangle_2", _tri(s / 2), t, action_origin=tri_origin(s / 2)),
    )
    return PieceSet("tangram7", pieces, twins=((0, 1), (5, 6)))


_REGISTRY: dict[str, Callable[[], PieceSet]] = {"tangram7": tangram7}
_CACHE: dict[str, PieceSet] = {}


def register_piece_set(name: str, factory: Callable[[], PieceSet]) -> None:
    """Make a piece set available by name (to configs, figure files and checkpoints)."""
    _REGISTRY[name] = factory
    _CACHE.pop(name, None)


def get_piece_set(name: str) -> PieceSet:
    """Return the registered piece set ``name``."""
    if name not in _REGISTRY:
        raise KeyError(f"unknown piece set {name!r}; registered: {sorted(_REGISTRY)}")
    if name not in _CACHE:
        _CACHE[name] = _REGISTRY[name]()
    return _CACHE[name]


def piece_set_names() -> list[str]:
    return sorted(_REGISTRY)
