"""Piece sets: the rigid parts a figure is assembled from, as data.

A piece set is an ordered tuple of pieces. A piece's identity everywhere in the
package is its index in that order, which is also the placement order (largest
first for the tangram). Outlines are polygons in metres, counter-clockwise, with
their area centroid at the origin, so a pose (x, y, theta) places the centroid at
(x, y) and rotates the outline by theta about it. A non-convex piece also carries
a convex decomposition (``parts``) whose union is its outline exactly: collision
meshes, overlap tests and the rasteriser work on the parts, so what is drawn and
scored is the true outline.

Sets defined here: ``tangram7``, ``cutlery`` (knife, spoon, fork) and ``soda3`` …
``soda6`` (interchangeable 66 mm cans). New part sets plug in through
:func:`register_piece_set`.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import shapely

from mrchaos.core.geometry import polygon_area, polygon_centroid, rigid_transform

__all__ = [
    "Piece",
    "PieceSet",
    "tangram7",
    "cutlery",
    "soda",
    "register_piece_set",
    "get_piece_set",
    "piece_set_names",
]


@dataclass(frozen=True)
class Piece:
    """One rigid part.

    Attributes:
        name: unique name within its set.
        outline: (V, 2) polygon, metres, counter-clockwise, centroid at the origin; convex
            unless ``parts`` is given.
        thickness: extrusion height in metres.
        symmetry: order of rotational symmetry (1 = none, 2 = 180 deg, 4 = 90 deg,
            0 = continuous, e.g. a disc).
        chiral: True when the mirror image is a different shape that a top-down
            suction gripper cannot produce (it cannot flip a part over).
        mass: kilograms; default from a plywood-like density.
        action_origin: the point (centroid frame, m) that a placement action positions.
            The reference code positions each tangram piece by its mesh origin, not its
            centroid; keeping that point makes the action grid's rounding identical.
        parts: convex polygons (same frame as ``outline`` before centring) whose union is
            the outline; None for a convex piece (its outline is its one part). Use
            :func:`piece_from_parts` to build a non-convex piece.
    """

    name: str
    outline: np.ndarray
    thickness: float
    symmetry: int = 1
    chiral: bool = False
    mass: float | None = None
    action_origin: tuple[float, float] = (0.0, 0.0)
    parts: tuple[np.ndarray, ...] | None = None

    def __post_init__(self) -> None:
        outline = np.asarray(self.outline, dtype=np.float64)
        if outline.ndim != 2 or outline.shape[1] != 2 or outline.shape[0] < 3:
            raise ValueError(f"piece {self.name!r}: outline must be (V>=3, 2), got {outline.shape}")
        if polygon_area(outline) < 0:
            outline = outline[::-1].copy()
        centre = polygon_centroid(outline)
        raw_parts = [outline] if self.parts is None else [np.asarray(q, dtype=np.float64) for q in self.parts]
        parts = []
        for q in raw_parts:
            q = q[::-1] if polygon_area(q) < 0 else q
            if not shapely.Polygon(q).equals(shapely.Polygon(q).convex_hull):
                raise ValueError(f"piece {self.name!r}: a part is not convex; give a convex decomposition")
            q = q - centre
            q.setflags(write=False)
            parts.append(q)
        outline = outline - centre
        outline.setflags(write=False)
        object.__setattr__(self, "outline", outline)
        object.__setattr__(self, "parts", tuple(parts))
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
        return _mirror(self.outline)

    @property
    def convex_parts(self) -> tuple[np.ndarray, ...]:
        """The convex parts whose union is the outline (the outline itself for a convex piece)."""
        assert self.parts is not None  # __post_init__ sets them
        return self.parts

    def mirrored_parts(self) -> tuple[np.ndarray, ...]:
        """Parts reflected about the y axis."""
        return tuple(_mirror(q) for q in self.convex_parts)


def _mirror(poly: np.ndarray) -> np.ndarray:
    return (poly * np.array([-1.0, 1.0]))[::-1].copy()


def piece_from_parts(name: str, parts: list[np.ndarray], thickness: float, **kwargs) -> Piece:
    """A (possibly non-convex) piece from convex parts that overlap or share edges; its
    outline is their union."""
    union = shapely.union_all([shapely.Polygon(q).buffer(0) for q in parts]).simplify(1e-7)
    if union.geom_type != "Polygon" or len(union.interiors):
        raise ValueError(f"piece {name!r}: its parts must join into one polygon without holes")
    return Piece(name, np.asarray(union.exterior.coords)[:-1], thickness, parts=tuple(parts), **kwargs)


@dataclass(frozen=True)
class PieceSet:
    """An ordered set of pieces. Index in ``pieces`` is the piece id and the placement order.

    ``twins`` groups interchangeable pieces (same shape): a piece may fill any
    slot of its group when rewards are computed.
    """

    name: str
    pieces: tuple[Piece, ...]
    twins: tuple[tuple[int, ...], ...] = field(default=())
    #: Piece sets of one kind share policies: a checkpoint trained on one member acts on
    #: any other (e.g. soda3 … soda6, whose pieces are all the same can). Default: the name.
    #: ("Family" is kept for the evaluation families, H-Normal and the rest.)
    kind: str = ""

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

        if not self.kind:
            object.__setattr__(self, "kind", self.name)

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

    def to_centroid(self, piece: np.ndarray, pose: np.ndarray, mirrored: np.ndarray | None = None) -> np.ndarray:
        """Poses (..., 3) of action origins -> centroid poses of the given pieces (``mirrored``:
        turned over, so the origin lies at its mirror image)."""
        return self._shift(piece, pose, -1.0, mirrored)

    def to_origin(self, piece: np.ndarray, pose: np.ndarray, mirrored: np.ndarray | None = None) -> np.ndarray:
        """Centroid poses (..., 3) -> poses of the pieces' action origins."""
        return self._shift(piece, pose, 1.0, mirrored)

    def _shift(self, piece: np.ndarray, pose: np.ndarray, sign: float, mirrored: np.ndarray | None) -> np.ndarray:
        pose = np.asarray(pose, dtype=np.float64)
        off = self.action_origins()[np.asarray(piece)]
        if mirrored is not None and np.any(mirrored):
            off = off * np.where(np.asarray(mirrored)[..., None], [-1.0, 1.0], [1.0, 1.0])
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

    @property
    def parts_per_piece(self) -> int:
        """K: the most convex parts of any piece (1 for convex sets)."""
        return max(len(p.convex_parts) for p in self.pieces)

    @property
    def part_piece(self) -> np.ndarray:
        """(P*K,) the piece of every padded part: parts are grouped by piece, in piece order."""
        return np.repeat(np.arange(len(self.pieces)), self.parts_per_piece)

    @property
    def raster_parts(self) -> np.ndarray | None:
        """What :func:`mrchaos.core.raster.rasterize` takes as ``parts`` for this set's footprints:
        :attr:`part_piece`, or None for a convex set (one part per piece)."""
        return self.part_piece if self.parts_per_piece > 1 else None

    def padded_parts(self, mirrored: np.ndarray | None = None) -> np.ndarray:
        """(P*K, Vmax, 2) convex parts, K per piece; a piece with fewer parts repeats its
        last one, shorter polygons repeat their last vertex. For convex sets this is
        :meth:`padded_outlines`."""
        k = self.parts_per_piece
        parts = [
            list(p.mirrored_parts() if (mirrored is not None and mirrored[i]) else p.convex_parts)
            for i, p in enumerate(self.pieces)
        ]
        vmax = max(len(q) for ps in parts for q in ps)
        out = np.zeros((len(self.pieces) * k, vmax, 2))
        for i, ps in enumerate(parts):
            ps = ps + [ps[-1]] * (k - len(ps))
            for j, q in enumerate(ps):
                out[i * k + j, : len(q)] = q
                out[i * k + j, len(q) :] = q[-1]
        return out

    @property
    def chiral(self) -> np.ndarray:
        """(P,) bool: pieces whose mirror image is another shape."""
        return np.array([p.chiral for p in self.pieces])

    def footprints(self, poses: np.ndarray, mirrored: np.ndarray | None = None) -> np.ndarray:
        """World polygons (..., P*K, Vmax, 2) of the parts of pieces at centroid poses (..., P, 3);
        ``mirrored`` (..., P) bool (or (P,) for all) selects the mirror image of a piece."""
        poses = np.repeat(np.asarray(poses), self.parts_per_piece, -2)
        if mirrored is None or np.asarray(mirrored).ndim <= 1 or not np.any(mirrored):
            return rigid_transform(
                self.padded_parts(None if mirrored is None or np.asarray(mirrored).ndim > 1 else mirrored), poses
            )
        both = np.stack([self.padded_parts(), self.padded_parts(np.ones(len(self.pieces), dtype=bool))])
        which = np.repeat(np.asarray(mirrored, dtype=np.int64), self.parts_per_piece, -1)
        return rigid_transform(both[which, np.arange(which.shape[-1])], poses)


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


def _ellipse(cx: float, a: float, b: float, n: int = 16) -> np.ndarray:
    """An n-gon of the ellipse's area (semi-axes a along x, b along y) centred at (cx, 0)."""
    t = np.arange(n) * 2 * math.pi / n
    k = math.sqrt(2 * math.pi / (n * math.sin(2 * math.pi / n)))  # polygon area = ellipse area
    return np.c_[cx + k * a * np.cos(t), k * b * np.sin(t)]


def cutlery() -> PieceSet:
    """A knife, a spoon and a fork (210, 177 and 195 mm long, 4 mm thick), lying along +x.

    The fork and the spoon are mirror-symmetric; the knife's edge curves up to the tip on
    one side only, so its mirror image is another knife (chiral). None has a rotational
    symmetry. Outlines are the unions of the convex parts listed here.
    """
    t = 0.004
    knife = piece_from_parts(
        "knife",
        [
            np.array([[0.0, -0.0085], [0.094, -0.0075], [0.094, 0.0075], [0.0, 0.0085]]),  # handle
            np.array(
                [[0.094, -0.010], [0.165, -0.010], [0.192, -0.005], [0.208, 0.004], [0.21, 0.010], [0.094, 0.010]]
            ),  # blade
        ],
        t,
        chiral=True,
    )
    spoon = piece_from_parts(
        "spoon",
        [
            np.array([[0.0, -0.007], [0.115, -0.003], [0.115, 0.003], [0.0, 0.007]]),  # handle
            _ellipse(0.145, 0.032, 0.021),  # bowl
        ],
        t,
    )
    tines = [
        np.array([[0.1495, y], [0.195, y], [0.195, y + 0.004], [0.1495, y + 0.004]])
        for y in (-0.011, -0.005, 0.001, 0.007)
    ]
    fork = piece_from_parts(
        "fork",
        [
            np.array([[0.0, -0.009], [0.105, -0.005], [0.105, 0.005], [0.0, 0.009]]),  # handle
            np.array([[0.105, -0.005], [0.135, -0.011], [0.135, 0.011], [0.105, 0.005]]),  # neck
            np.array([[0.135, -0.011], [0.150, -0.011], [0.150, 0.011], [0.135, 0.011]]),  # head
            *tines,
        ],
        t,
    )
    return PieceSet("cutlery", (knife, spoon, fork))


#: Diameter and height of a 330 ml soda can (m).
CAN_DIAMETER, CAN_HEIGHT = 0.066, 0.122


def soda(n: int = 6) -> PieceSet:
    """``n`` standing soda cans: discs 66 mm across (16-gons of the disc's area), 122 mm
    tall, continuously symmetric and all interchangeable (one twin group)."""
    if not 1 <= n <= 16:
        raise ValueError(f"soda: 1 to 16 cans, got {n}")
    disc = _ellipse(0.0, CAN_DIAMETER / 2, CAN_DIAMETER / 2)
    cans = tuple(Piece(f"can_{i + 1}", disc, CAN_HEIGHT, symmetry=0) for i in range(n))
    return PieceSet(f"soda{n}", cans, twins=(tuple(range(n)),), kind="soda")


_REGISTRY: dict[str, Callable[[], PieceSet]] = {
    "tangram7": tangram7,
    "cutlery": cutlery,
    **{f"soda{n}": functools.partial(soda, n) for n in range(3, 7)},
}
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
