"""Author the built-in library of human-designed tangram figures.

Run ``python tools/author_library.py`` to rebuild ``mrchaos/data/library.json``
deterministically; ``--sheet PATH.png`` also writes a contact sheet to look at.

Every figure is written in a small placement language (see :class:`Build`).
Pieces are placed either by a corner and edge directions in multiples of 45
degrees (:meth:`Build.tri`, :meth:`Build.hyp`, :meth:`Build.square`,
:meth:`Build.para`), or by their corners on a 25 mm grid (:meth:`Build.grid`),
on which all corners lie when triangle hypotenuses, square diagonals and the
parallelogram's long side run along the axes. A new piece is anchored on corners
of pieces already placed or on points along their edges (grid points, or half
steps for a limb that overlaps a body by half an edge). Coordinates are therefore
exact (computed from the piece dimensions, never typed as decimals), pieces meet
flush as in tangram books, and the checks below can demand zero overlap rather
than a tolerance.

Lengths inside the language are millimetres of the 100 mm tangram:

* ``A`` = 35.36 mm: small-triangle leg, square side, parallelogram short side;
* ``B`` = 50 mm: medium-triangle leg, small-triangle hypotenuse, parallelogram long side;
* ``C`` = 70.71 mm: large-triangle leg, medium-triangle hypotenuse;
* ``D`` = 100 mm: large-triangle hypotenuse;
* ``H`` = 25 mm: the pitch of the grid that :meth:`Build.grid` places corners on.

A figure may be authored with either handedness of the parallelogram; when
the recovered pose says the piece is flipped, the whole figure is reflected
(x -> -x), because a suction robot cannot turn the piece over.

Each figure is checked (:func:`check_figure`), the library is written in the
interchange format with millimetre units (:func:`write_library` explains why not
``save_figures``), and the written file is reloaded and compared with the exact
figures pixel for pixel (:func:`check_stored`). Families are not stored: the
perimeter rule (:mod:`mrchaos.figures.families`) assigns them.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import shapely
from shapely.ops import unary_union

from mrchaos.figures.families import FamilyRule, family_of, silhouette_perimeter_px
from mrchaos.figures.figure import Figure, figure_from_polygons
from mrchaos.figures.pieces import PieceSet, tangram7

A = 100.0 / (2.0 * math.sqrt(2.0))
B = 50.0
C = 2.0 * A
D = 100.0
#: Grid pitch (mm) of :meth:`Build.grid`: half a small-triangle hypotenuse.
H = 25.0

#: Largest |coordinate| a centred figure may reach (m): leaves margin in the 0.26 m view.
MAX_REACH = 0.115
#: Pieces closer than this (m) touch.
TOUCH_TOL = 1e-7
#: Largest pairwise overlap (m^2) a figure may have; exact placement gives ~1e-12.
OVERLAP_TOL = 1e-8
#: Most single-vertex joints a figure may need to hold together.
MAX_POINT_JOINTS = 2
#: Shortest shared boundary (m) that counts as an edge contact rather than a point contact.
EDGE_CONTACT = 1e-3

LIBRARY_PATH = Path(__file__).resolve().parents[1] / "mrchaos" / "data" / "library.json"

Point = np.ndarray


def pt(x: float, y: float) -> Point:
    """A point in millimetres."""
    return np.array([x, y], dtype=np.float64)


def pol(length: float, deg: float) -> Point:
    """The vector of ``length`` mm pointing ``deg`` degrees counter-clockwise from +x."""
    r = math.radians(deg)
    return np.array([length * math.cos(r), length * math.sin(r)])


_LEGS = {"L": C, "M": B, "S": A}


class Build:
    """Collects the seven pieces of one figure, in any order of placement.

    Each placing method returns the piece's vertices (mm, counter-clockwise) so
    that later pieces can be anchored on them; index ``[k]`` is vertex k as the
    method's docstring numbers it.
    """

    def __init__(self) -> None:
        self.pieces: dict[str, list[np.ndarray]] = {"L": [], "Q": [], "P": [], "M": [], "S": []}

    def _add(self, kind: str, verts: list[Point]) -> np.ndarray:
        """Record a piece of ``kind`` with corners ``verts`` (mm) and return them as an array."""
        v = np.array(verts, dtype=np.float64)
        self.pieces[kind].append(v)
        return v

    def tri(self, size: str, corner: Point, deg: float) -> np.ndarray:
        """Right triangle of ``size`` 'L', 'M' or 'S' with its right angle at ``corner``.

        Legs run along ``deg`` and ``deg + 90``; vertices: 0 corner, 1 end of the
        first leg, 2 end of the second leg.
        """
        leg = _LEGS[size]
        c = np.asarray(corner, dtype=np.float64)
        return self._add(size, [c, c + pol(leg, deg), c + pol(leg, deg + 90)])

    def hyp(self, size: str, p: Point, deg: float) -> np.ndarray:
        """Right triangle whose hypotenuse starts at p along ``deg``; the right angle lies to its left.

        Vertices: 0 p, 1 hypotenuse end, 2 right-angle corner.
        """
        leg = _LEGS[size]
        p = np.asarray(p, dtype=np.float64)
        q = p + pol(leg * math.sqrt(2.0), deg)
        return self._add(size, [p, q, p + pol(leg, deg + 45)])

    def square(self, corner: Point, deg: float) -> np.ndarray:
        """Square with a corner at ``corner`` and sides along ``deg`` and ``deg + 90``.

        Vertices: 0 corner, 1 along ``deg``, 2 opposite, 3 along ``deg + 90``.
        """
        c = np.asarray(corner, dtype=np.float64)
        u, v = pol(A, deg), pol(A, deg + 90)
        return self._add("Q", [c, c + u, c + u + v, c + v])

    def para(self, p: Point, long_deg: float, short_deg: float) -> np.ndarray:
        """Parallelogram with a vertex at p, its long side (50 mm) along ``long_deg`` and
        its short side (35.36 mm) along ``short_deg``; the two must differ by 45 or 135 deg.

        Vertices: 0 p, 1 end of the long side, 2 opposite p, 3 end of the short side.
        Either handedness is accepted; :func:`make_figure` fixes a flipped one.
        """
        diff = (short_deg - long_deg) % 360.0
        if min(abs(diff - x) for x in (45, 135, 225, 315)) > 1e-9:
            raise ValueError(f"parallelogram sides at {long_deg} and {short_deg} deg are not 45/135 deg apart")
        p = np.asarray(p, dtype=np.float64)
        u, v = pol(B, long_deg), pol(A, short_deg)
        return self._add("P", [p, p + u, p + u + v, p + v])

    def grid(self, kind: str, *corners: tuple[float, float]) -> np.ndarray:
        """Place a piece by its corners on the 25 mm grid (units of H = 25 mm).

        With triangle hypotenuses, square diagonals and the parallelogram's long side
        along the axes, every corner of every piece lies on this grid, so most figures
        are drawn as integer coordinates. The corners must form the piece ``kind``
        ('L', 'M', 'S', 'Q' or 'P'); :func:`make_figure` rejects any other shape.
        """
        if kind not in self.pieces:
            raise ValueError(f"unknown piece kind {kind!r}")
        return self._add(kind, [H * np.asarray(c, dtype=np.float64) for c in corners])

    def polygons(self) -> list[np.ndarray]:
        """The seven pieces in tangram7 order, in metres."""
        want = {"L": 2, "Q": 1, "P": 1, "M": 1, "S": 2}
        got = {k: len(v) for k, v in self.pieces.items()}
        if got != want:
            raise ValueError(f"need pieces {want}, got {got}")
        order = self.pieces["L"] + self.pieces["Q"] + self.pieces["P"] + self.pieces["M"] + self.pieces["S"]
        return [v * 1e-3 for v in order]


# --------------------------------------------------------------------------- checks


class LibraryError(ValueError):
    """A figure of the library is not an exact, valid tangram."""


def _cross(u: np.ndarray, v: np.ndarray) -> float:
    """z component of the cross product of 2-vectors."""
    return float(u[0] * v[1] - u[1] * v[0])


def _shared_length(p: np.ndarray, q: np.ndarray, eps: float = 1e-9) -> float:
    """Total length (m) of boundary that convex polygons p and q share, computed edge by edge.

    Done analytically because shapely's boundary intersection of exactly touching
    float polygons can come back empty or as stray points.
    """
    total = 0.0
    for i in range(len(p)):
        a, b = p[i], p[(i + 1) % len(p)]
        d = b - a
        length = float(np.hypot(*d))
        u = d / length
        for j in range(len(q)):
            c, e = q[j], q[(j + 1) % len(q)]
            # only collinear edges can share length; anything else meets at a point at most
            if abs(_cross(u, c - a)) > eps or abs(_cross(u, e - a)) > eps:
                continue
            s0, s1 = sorted((float(np.dot(c - a, u)), float(np.dot(e - a, u))))
            total += max(0.0, min(s1, length) - max(s0, 0.0))
    return total


def contacts(fig: Figure) -> tuple[list[tuple[int, int]], list[tuple[int, int]]]:
    """Pairs of pieces that touch along an edge, and pairs that touch only at a point."""
    polys = [fig.piece_polygon(i) for i in range(len(fig.piece_set))]
    sp = [shapely.Polygon(p) for p in polys]
    edge, point = [], []
    for i in range(len(polys)):
        for j in range(i + 1, len(polys)):
            if sp[i].distance(sp[j]) > TOUCH_TOL:
                continue
            (edge if _shared_length(polys[i], polys[j]) > EDGE_CONTACT else point).append((i, j))
    return edge, point


def check_figure(fig: Figure) -> None:
    """Raise :class:`LibraryError` unless the figure is an exact, connected, centred tangram."""
    where = f"figure {fig.id!r}"
    if fig.has_mirrored:
        raise LibraryError(f"{where}: the parallelogram is flipped")
    overlap = fig.overlap_area()
    if overlap >= OVERLAP_TOL:
        raise LibraryError(f"{where}: pieces overlap by {overlap * 1e6:.3f} mm^2")
    verts = np.concatenate([fig.piece_polygon(i) for i in range(len(fig.piece_set))])
    if np.abs(verts).max() > MAX_REACH:
        raise LibraryError(f"{where}: reaches {np.abs(verts).max() * 1e3:.1f} mm from the centre")
    centre = (verts.min(0) + verts.max(0)) / 2
    if np.abs(centre).max() > 1e-9:
        raise LibraryError(f"{where}: bounding box centred at {centre}")
    edge, point = contacts(fig)
    n = len(fig.piece_set)
    # union-find over the contact graph
    parent = list(range(n))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i, j in edge + point:
        parent[root(i)] = root(j)
    groups = {root(i) for i in range(n)}
    if len(groups) != 1:
        raise LibraryError(f"{where}: pieces fall apart into {len(groups)} groups")
    # Hanging a part on by a single vertex is allowed (the books do it, e.g. a head on
    # a neck), but a figure held together mostly by points would not read as one shape.
    parent = list(range(n))
    for i, j in edge:
        parent[root(i)] = root(j)
    clusters = len({root(i) for i in range(n)})
    if clusters > MAX_POINT_JOINTS + 1:
        raise LibraryError(f"{where}: needs {clusters - 1} point joints to hold together (at most {MAX_POINT_JOINTS})")
    union = unary_union([shapely.Polygon(fig.piece_polygon(i)) for i in range(n)])
    if abs(union.area - fig.piece_set.total_area) > 1e-9:
        raise LibraryError(f"{where}: union area {union.area * 1e6:.1f} mm^2 != total piece area")
    # shapely splits the union where pieces meet at a single point; those parts must
    # still touch each other, i.e. the silhouette is one shape
    parts = list(getattr(union, "geoms", [union]))
    reached, frontier = {0}, [0]
    while frontier:
        k = frontier.pop()
        for m in range(len(parts)):
            if m not in reached and parts[k].distance(parts[m]) <= TOUCH_TOL:
                reached.add(m)
                frontier.append(m)
    if len(reached) != len(parts):
        raise LibraryError(f"{where}: the silhouette falls apart into separate shapes")
    fig.validate()


# --------------------------------------------------------------------------- building


def make_figure(
    ps: PieceSet, fig_id: str, name: str, draw: Callable[[Build], None], turn: float = 0.0, check: bool = True
) -> Figure:
    """Run a figure's drawing function and turn the result into a centred, unflipped figure.

    ``turn`` rotates the whole drawing (degrees, counter-clockwise), so one pose can
    be drawn on the grid and shown leaning. With ``check`` False a broken figure is
    returned anyway (for drawing while authoring).
    """
    b = Build()
    draw(b)
    polys = b.polygons()
    if turn:
        c, s = math.cos(math.radians(turn)), math.sin(math.radians(turn))
        rot = np.array([[c, s], [-s, c]])  # row vectors: v @ rot rotates v by +turn
        polys = [p @ rot for p in polys]
    # a 1 um fit tolerance (the loader allows 0.5 mm) proves each drawn polygon is the piece
    fig = figure_from_polygons(ps, polys, fig_id, name=name, tol=1e-6)
    if fig.has_mirrored:
        polys = [p * np.array([-1.0, 1.0]) for p in polys]
    verts = np.concatenate(polys)
    centre = (verts.min(0) + verts.max(0)) / 2
    polys = [p - centre for p in polys]
    fig = figure_from_polygons(ps, polys, fig_id, name=name, tol=1e-6)
    if check:
        check_figure(fig)
    return fig


FIGURES: list[tuple[str, str, Callable[[Build], None], float]] = []


def figure(fig_id: str, name: str, turn: float = 0.0) -> Callable[[Callable[[Build], None]], Callable[[Build], None]]:
    """Register a drawing function as library figure ``fig_id`` called ``name``, turned by ``turn`` degrees."""

    def register(draw: Callable[[Build], None]) -> Callable[[Build], None]:
        FIGURES.append((fig_id, name, draw, turn))
        return draw

    return register


def shared_boundary_mm(fig: Figure) -> dict[tuple[int, int], float]:
    """Shared boundary length (mm) of every pair of pieces that touch along an edge."""
    polys = [fig.piece_polygon(i) for i in range(len(fig.piece_set))]
    out = {}
    for i in range(len(polys)):
        for j in range(i + 1, len(polys)):
            length = _shared_length(polys[i], polys[j])
            if length > EDGE_CONTACT:
                out[(i, j)] = round(length * 1e3, 1)
    return out


def perimeter_px(fig: Figure, rule: FamilyRule = FamilyRule()) -> float:
    """The silhouette perimeter the family rule sees (pixels)."""
    return silhouette_perimeter_px(fig.silhouette(rule.view).numpy())


# --------------------------------------------------------------------------- figures
#
# Grid figures (Build.grid) are in units of H = 25 mm; y points up. A figure may face
# either way: make_figure reflects it when the parallelogram comes out flipped.


def _two_a_square(b: Build, o: Point) -> None:
    """Fill the 70.71 mm square with lower-left corner ``o`` with the five small pieces."""
    b.square(o, 0)
    b.hyp("M", o + pt(C, C), 180)
    b.tri("S", o + pt(0, A), 0)
    b.tri("S", o + pt(C, 0), 90)
    b.para(o + pt(A, 0), 45, 90)


def _strip(b: Build, o: Point) -> None:
    """Fill the 35 x 141 mm strip with lower-left corner ``o`` with the five small pieces."""
    b.square(o, 0)
    b.tri("S", o + pt(A, A), 270)
    b.hyp("M", o + pt(A, 0), 0)
    b.para(o + pt(2 * A, A), -45, 0)
    b.tri("S", o + pt(4 * A, A), 180)


def _column(b: Build, o: Point) -> None:
    """Fill the 35 x 106 mm upright column above ``o`` with square, two small triangles, parallelogram."""
    b.square(o, 0)
    b.tri("S", o + pt(A, A), 90)
    b.para(o + pt(0, A), 45, 90)
    b.tri("S", o + pt(0, 3 * A), 270)


# ---- geometric shapes and letters


@figure("square", "Square")
def _square(b: Build) -> None:
    b.hyp("L", pt(0, 0), 0)
    b.hyp("L", pt(0, D), -90)
    b.tri("M", pt(D, D), 180)
    b.hyp("S", pt(D, 0), 90)
    b.square(pt(B, B), -45)
    b.tri("S", pt(B, B), 45)
    b.para(pt(25, 75), 0, 135)


@figure("rectangle", "Rectangle")
def _rectangle(b: Build) -> None:
    b.hyp("L", pt(0, 0), 45)
    b.hyp("L", pt(C, C), 225)
    _two_a_square(b, pt(C, 0))


@figure("triangle", "Triangle")
def _triangle(b: Build) -> None:
    b.tri("L", pt(0, C), 0)
    b.tri("L", pt(C, 0), 0)
    _two_a_square(b, pt(0, 0))


@figure("parallelogram", "Parallelogram")
def _parallelogram(b: Build) -> None:
    b.tri("L", pt(C, 0), 90)
    _two_a_square(b, pt(C, 0))
    b.tri("L", pt(2 * C, C), 270)


@figure("trapezoid", "Trapezoid")
def _trapezoid(b: Build) -> None:
    b.tri("L", pt(C, 0), 90)
    _two_a_square(b, pt(C, 0))
    b.tri("L", pt(2 * C, 0), 0)


@figure("letter_t", "Letter T")
def _letter_t(b: Build) -> None:
    _strip(b, pt(-2 * A, C))
    b.tri("L", pt(-A, 0), 0)
    b.tri("L", pt(A, C), 180)


# ---- buildings


@figure("house", "House")
def _house(b: Build) -> None:
    _two_a_square(b, pt(0, 0))
    b.tri("L", pt(A, C), 90)
    b.tri("L", pt(A, C), 0)


@figure("church", "Church")
def _church(b: Build) -> None:
    # tower: two large triangles and a medium-triangle spire; nave: the column laid down
    b.hyp("L", pt(0, 0), 45)
    b.hyp("L", pt(C, C), 225)
    b.hyp("M", pt(0, C), 0)
    b.square(pt(C, 0), 0)
    b.tri("S", pt(C + A, A), 270)
    b.para(pt(C + A, 0), 45, 0)
    b.tri("S", pt(C + 3 * A, 0), 90)


@figure("lighthouse", "Lighthouse")
def _lighthouse(b: Build) -> None:
    _column(b, pt(0, 0))
    b.tri("L", pt(0, 0), 90)
    b.tri("L", pt(A, 0), 0)
    b.hyp("M", pt(A / 2 - C / 2, 3 * A), 0)


@figure("bridge", "Bridge")
def _bridge(b: Build) -> None:
    b.tri("L", pt(0, C), 270)
    b.tri("L", pt(2 * C, C), 180)
    _strip(b, pt(0, C))


# ---- boats


@figure("sailboat", "Sailboat")
def _sailboat(b: Build) -> None:
    # hull: small triangle, square, small triangle, parallelogram; mainsail, jib, topsail
    b.tri("S", pt(A, 0), 180)
    b.square(pt(A, -A), 0)
    b.tri("S", pt(2 * A, 0), 270)
    b.para(pt(2 * A, -A), 45, 0)
    mast = pt(2 * A, 0)
    b.tri("L", mast, 90)
    b.hyp("L", mast + pt(0, D), 270)
    b.tri("M", pt(2 * A, C), 90)


@figure("steamship", "Steamship")
def _steamship(b: Build) -> None:
    b.hyp("L", pt(D, 0), 180)
    b.hyp("L", pt(B, -B), 0)
    b.tri("M", pt(150, 0), 180)
    b.square(pt(B, 0), 0)
    b.tri("S", pt(B + A, 0), 0)
    b.tri("S", pt(B, 0), 90)
    b.para(pt(B, A), 45, 0)


# ---- objects


@figure("boot", "Boot")
def _boot(b: Build) -> None:
    b.hyp("L", pt(0, A), 45)
    b.hyp("L", pt(C, A + C), 225)
    b.square(pt(0, 0), 0)
    b.tri("S", pt(A, A), 270)
    b.para(pt(A, 0), 45, 0)
    b.hyp("M", pt(2 * A, 0), 0)
    b.tri("S", pt(2 * A, A), 0)


@figure("arrow", "Arrow")
def _arrow(b: Build) -> None:
    b.tri("L", pt(3 * A, 0), 0)
    b.tri("L", pt(3 * A, 0), 270)
    b.square(pt(2 * A, -A / 2), 0)
    b.tri("S", pt(0, A / 2), 270)
    b.para(pt(0, -A / 2), 45, 0)
    b.tri("S", pt(2 * A, -A / 2), 90)
    # the fletching hangs on the end of the shaft by its tip, as in the books
    b.tri("M", pt(0, 0), 135)


@figure("teapot", "Teapot")
def _teapot(b: Build) -> None:
    b.tri("L", pt(0, 0), 0)
    b.tri("L", pt(C, C), 180)
    b.tri("S", pt(A, C), 0)
    b.tri("S", pt(A, C), 90)
    b.para(pt(C, 0), 45, 90)
    b.hyp("M", pt(0, 0), 90)
    b.square(pt(A / 2, -A), 0)


@figure("candle", "Candle")
def _candle(b: Build) -> None:
    b.square(pt(0, 0), 0)
    b.tri("S", pt(0, A), 0)
    b.tri("S", pt(A, 2 * A), 180)
    # the flame sits half off the wick so that it flickers sideways
    b.para(pt(A / 2, 2 * A), 45, 0)
    b.hyp("M", pt(A / 2 + C / 2, 0), 180)
    b.tri("L", pt(A / 2, -A - C), 0)
    b.tri("L", pt(A / 2, -A - C), 90)


@figure("rocket", "Rocket")
def _rocket(b: Build) -> None:
    b.tri("L", pt(0, 0), 0)
    b.tri("L", pt(C, C), 180)
    b.hyp("M", pt(0, C), 0)
    b.tri("S", pt(0, 0), 90)
    b.tri("S", pt(C, 0), 0)
    b.square(pt(A / 2, -A), 0)
    b.para(pt(A / 2, -A), 225, 0)


@figure("umbrella", "Umbrella")
def _umbrella(b: Build) -> None:
    b.tri("L", pt(0, 0), 0)
    b.tri("L", pt(0, 0), 90)
    b.square(pt(-A / 2, -A), 0)
    b.tri("S", pt(-A / 2, -A), 270)
    b.tri("S", pt(A / 2, -2 * A), 90)
    b.para(pt(A / 2, -2 * A), 225, 180)
    b.hyp("M", pt(-A / 2, -3 * A), 180)


# ---- animals


@figure("cat", "Cat")
def _cat(b: Build) -> None:
    chest = b.tri("L", pt(C, 0), 90)
    b.tri("L", pt(C, 0), 0)
    head = b.square(chest[1] + pol(A, 225), 45)
    b.tri("S", head[2], 135)
    b.tri("S", head[2], -45)
    b.para(pt(2 * C, 0), 0, 135)
    b.tri("M", pt(0, 0), 45)


@figure("cat_sitting", "Cat sitting")
def _cat_sitting(b: Build) -> None:
    b.tri("L", pt(0, 0), 0)
    b.tri("L", pt(0, 0), 90)
    # the head stands on the top of the body by one corner, ears on its upper sides
    head = b.square(pt(0, C), 45)
    b.tri("S", head[2], 135)
    b.tri("S", head[2], -45)
    b.para(pt(C, 0), 135, 90)
    b.tri("M", pt(-C, 0), 45)


@figure("fish", "Fish")
def _fish(b: Build) -> None:
    b.hyp("L", pt(0, -B), 90)
    back = b.hyp("L", pt(0, B), 270)
    tail = back[2]
    # forked tail: two small triangles meeting the body at one point
    b.hyp("S", tail, 45)
    b.hyp("S", tail + pt(A, -A), 135)
    b.tri("M", pt(0, B), -45)
    b.para(pt(0, -B), 45, 270)
    b.square(pt(0, -B), 135)


@figure("swan", "Swan")
def _swan(b: Build) -> None:
    b.grid("L", (0, 0), (4, 0), (2, 2))
    b.grid("L", (4, 0), (4, 4), (2, 2))
    b.grid("P", (0, 0), (0, 2), (1, 3), (1, 1))
    b.grid("Q", (0, 2), (1, 3), (0, 4), (-1, 3))
    b.grid("S", (-2, 4), (0, 4), (-1, 3))
    b.grid("M", (4, 2), (6, 2), (4, 4))
    b.grid("S", (4, 0), (4, 2), (5, 1))


@figure("hen", "Hen")
def _hen(b: Build) -> None:
    b.grid("L", (0, 0), (4, 0), (2, -2))
    b.grid("L", (0, 0), (4, 0), (2, 2))
    b.grid("Q", (0, 0), (1, 1), (0, 2), (-1, 1))
    b.grid("S", (1, 1), (1, 3), (0, 2))
    b.grid("S", (-1, -1), (-1, 1), (0, 0))
    b.grid("M", (3, 1), (5, -1), (5, 1))
    b.grid("P", (2, -4), (2, -2), (1, -1), (1, -3))


@figure("bird", "Bird")
def _bird(b: Build) -> None:
    b.grid("P", (0, 0), (2, 0), (3, 1), (1, 1))
    # wings hinge on the body at single points, one raised and one lowered
    b.grid("L", (2, 1), (2, 5), (4, 3))
    b.grid("L", (1, -4), (1, 0), (3, -2))
    b.grid("Q", (0, 0), (1, 1), (0, 2), (-1, 1))
    b.grid("S", (-2, 2), (0, 2), (-1, 1))
    b.grid("M", (2, 0), (4, 2), (4, 0))
    b.grid("S", (4, 1), (4, 3), (5, 2))


@figure("heron", "Heron")
def _heron(b: Build) -> None:
    b.grid("L", (0, 0), (4, 0), (2, -2))
    b.grid("P", (2, -4), (2, -2), (1, -1), (1, -3))
    b.grid("S", (0, -4), (2, -4), (1, -3))
    b.grid("M", (0, 0), (0, 2), (2, 0))
    b.grid("Q", (1, 1), (2, 2), (1, 3), (0, 2))
    b.grid("S", (-1, 3), (1, 3), (0, 2))
    b.grid("L", (3, 0), (7, 0), (5, 2))


@figure("rabbit", "Rabbit")
def _rabbit(b: Build) -> None:
    b.grid("L", (0, 0), (4, 0), (2, 2))
    b.grid("L", (2, 2), (6, 2), (4, 0))
    b.grid("M", (4, 0), (6, 0), (6, 2))
    b.grid("S", (6, 1), (6, 3), (7, 2))
    b.grid("Q", (1, 1), (2, 2), (1, 3), (0, 2))
    b.grid("P", (0, 2), (0, 4), (1, 5), (1, 3))
    b.grid("S", (2, 2), (2, 4), (1, 3))


@figure("dog", "Dog")
def _dog(b: Build) -> None:
    b.grid("L", (0, 0), (4, 0), (2, -2))
    # the front leg hangs half off the chest so the dog stands apart from its body
    b.grid("P", (0.5, -2.5), (0.5, -0.5), (-0.5, 0.5), (-0.5, -1.5))
    b.grid("L", (5, -3), (5, 1), (3, -1))
    b.grid("M", (0, 0), (2, 0), (0, 2))
    b.grid("Q", (1, 1), (2, 2), (1, 3), (0, 2))
    b.grid("S", (-1, 3), (1, 3), (0, 2))
    b.grid("S", (5, 0), (5, 2), (6, 1))


@figure("fox", "Fox")
def _fox(b: Build) -> None:
    b.grid("L", (0, 0), (4, 0), (2, -2))
    b.grid("P", (1, -3), (1, -1), (0, 0), (0, -2))
    b.grid("L", (3.5, -0.5), (7.5, -0.5), (5.5, 1.5))
    b.grid("M", (3.5, -0.5), (5.5, -0.5), (3.5, -2.5))
    b.grid("S", (-0.5, 0), (1.5, 0), (0.5, 1))
    b.grid("Q", (-0.5, 0), (0.5, 1), (-0.5, 2), (-1.5, 1))
    b.grid("S", (0.5, 1), (0.5, 3), (-0.5, 2))


@figure("horse", "Horse")
def _horse(b: Build) -> None:
    b.grid("L", (0, 0), (4, 0), (2, -2))
    b.grid("L", (2, -2), (6, -2), (4, 0))
    b.grid("P", (2, -4), (2, -2), (1, -1), (1, -3))
    b.grid("M", (6, -2), (6, -4), (4, -2))
    b.grid("S", (0, 0), (2, 0), (1, 1))
    b.grid("Q", (0, 0), (1, 1), (0, 2), (-1, 1))
    b.grid("S", (5, -1), (5, 1), (4, 0))


@figure("giraffe", "Giraffe")
def _giraffe(b: Build) -> None:
    b.grid("L", (0, 0), (4, 0), (2, -2))
    b.grid("M", (0, 0), (2, 0), (0, 2))
    b.grid("P", (1, 1), (1, 3), (0, 4), (0, 2))
    b.grid("Q", (1, 3), (2, 4), (1, 5), (0, 4))
    b.grid("S", (-1, 5), (1, 5), (0, 4))
    b.grid("L", (-1.5, -2.5), (-1.5, 1.5), (0.5, -0.5))
    b.grid("S", (4, -2), (4, 0), (3, -1))


@figure("kangaroo", "Kangaroo")
def _kangaroo(b: Build) -> None:
    b.grid("L", (0, 0), (0, 4), (2, 2))
    b.grid("Q", (1, 3), (2, 4), (1, 5), (0, 4))
    b.grid("S", (0, 4), (0, 6), (1, 5))
    b.grid("L", (0, -3), (0, 1), (-2, -1))
    b.grid("M", (0, 0), (2, 0), (0, -2))
    b.grid("P", (0, -2), (2, -2), (3, -1), (1, -1))
    b.grid("S", (2, 2), (4, 2), (3, 1))


@figure("elephant", "Elephant")
def _elephant(b: Build) -> None:
    b.tri("L", pt(0, 0), 0)
    b.tri("L", pt(C, C), 180)
    b.tri("S", pt(0, 0), 270)
    b.tri("S", pt(C, 0), 180)
    b.square(pt(-A, C - A), 0)
    b.para(pt(-A, C - A), 225, 0)
    b.tri("M", pt(0, C), 90)


@figure("turtle", "Turtle")
def _turtle(b: Build) -> None:
    b.tri("L", pt(0, 0), 0)
    b.tri("L", pt(0, 0), 90)
    b.tri("S", pt(-C, 0), 270)
    b.tri("S", pt(C, 0), 180)
    b.hyp("M", pt(A, 0), 180)
    b.square(pt(-C, 0) + pol(A / 2, 45), 45)
    b.para(pt(C, 0), 0, 135)


# ---- people
#
# Most people share a torso and head: a large triangle with its hypotenuse as the
# shoulders (front view) or the back (side view), and the square as a diamond
# standing on it by one corner. Limbs overlap the torso by a grid step or half a
# diagonal so that the figures stay as loose as the book figures they imitate.


def _profile(b: Build) -> None:
    """Side-view torso (back at x = 0, chest to the right) with the head on top."""
    b.grid("L", (0, 0), (0, 4), (2, 2))
    b.grid("Q", (0, 4), (1, 5), (0, 6), (-1, 5))


def _front(b: Build) -> None:
    """Front-view torso (shoulders 100 mm wide), head and a large-triangle skirt."""
    b.hyp("L", pt(B, 0), 180)
    b.square(pt(0, 0), 45)
    b.grid("L", (0, -2), (-2, -4), (2, -4))


@figure("dancer", "Dancer")
def _dancer(b: Build) -> None:
    _front(b)
    b.tri("S", pt(-B - (A - 25), 0), 0)
    b.tri("S", pt(B + (A - 25), 0), 90)
    b.para(pt(-25, -D), 225, 0)
    b.tri("M", pt(25, -D), -90)


@figure("waving_girl", "Girl waving")
def _waving_girl(b: Build) -> None:
    _front(b)
    b.tri("S", pt(B + (A - 25), 0), 90)
    b.grid("S", (-2, -2), (-2, 0), (-1, -1))
    b.para(pt(-25, -D), 225, 0)
    b.grid("M", (1, -4), (1, -6), (3, -4))


@figure("walking_woman", "Woman walking")
def _walking_woman(b: Build) -> None:
    _front(b)
    b.grid("S", (-2, -2), (-2, 0), (-1, -1))
    b.grid("S", (2, -2), (2, 0), (1, -1))
    b.para(pt(-25, -D), 225, 0)
    b.grid("M", (1, -4), (3, -4), (3, -6))


@figure("running_woman", "Woman running")
def _running_woman(b: Build) -> None:
    _front(b)
    b.tri("S", pt(B + (A - 25), 0), 90)
    b.grid("S", (-2, -2), (-2, 0), (-1, -1))
    b.grid("P", (-2, -4), (0, -4), (-1, -5), (-3, -5))
    b.grid("M", (1, -4), (3, -4), (3, -6))


@figure("runner", "Runner")
def _runner(b: Build) -> None:
    _profile(b)
    b.grid("S", (2, 2), (2, 4), (1, 3))
    b.grid("S", (0, 1), (0, 3), (-1, 2))
    b.grid("M", (1.5, 1.5), (3.5, 3.5), (3.5, 1.5))
    b.grid("P", (2.5, -1.5), (2.5, 0.5), (3.5, 1.5), (3.5, -0.5))
    b.grid("L", (0, -3), (0, 1), (-2, -1))


@figure("skater", "Skater", turn=-45)
def _skater(b: Build) -> None:
    # the runner's stride, arms swung back and the whole body leaning into the glide
    _profile(b)
    b.grid("S", (2, 2), (2, 4), (1, 3))
    b.grid("S", (0, 2), (0, 4), (-1, 3))
    b.grid("L", (0, -3), (0, 1), (-2, -1))
    b.grid("M", (1.5, 1.5), (3.5, 3.5), (3.5, 1.5))
    b.grid("P", (2.5, -1.5), (2.5, 0.5), (3.5, 1.5), (3.5, -0.5))


@figure("hurdler", "Hurdler")
def _hurdler(b: Build) -> None:
    _profile(b)
    b.grid("S", (2, 2), (2, 4), (1, 3))
    b.grid("S", (0, 2), (0, 4), (-1, 3))
    b.grid("L", (1.5, 1.5), (5.5, 1.5), (3.5, 3.5))
    b.grid("M", (0, 0), (-2, 0), (0, -2))
    b.grid("P", (-2, -2), (0, -2), (-1, -1), (-3, -1))


@figure("footballer", "Footballer")
def _footballer(b: Build) -> None:
    _profile(b)
    b.grid("S", (2, 2), (2, 4), (1, 3))
    b.grid("S", (0, 1), (0, 3), (-1, 2))
    b.grid("P", (0, -2), (0, 0), (1, 1), (1, -1))
    b.grid("L", (1.5, 1.5), (5.5, 1.5), (3.5, 3.5))
    b.grid("M", (-2, -2), (0, -2), (-2, 0))


@figure("old_man", "Old man with a cane")
def _old_man(b: Build) -> None:
    _profile(b)
    b.grid("S", (2, 0), (2, 2), (1, 1))
    b.grid("P", (2, -1), (2, 1), (3, 2), (3, 0))
    b.grid("S", (0, 1), (0, 3), (-1, 2))
    b.grid("L", (0, -3), (0, 1), (-2, -1))
    b.grid("M", (0, 0), (0, -2), (2, -2))


@figure("sitting_man", "Man sitting")
def _sitting_man(b: Build) -> None:
    _profile(b)
    b.grid("S", (2, 2), (2, 4), (1, 3))
    b.grid("S", (0, 1), (0, 3), (-1, 2))
    b.grid("L", (-1, -1), (3, -1), (1, 1))
    b.grid("M", (2, 0), (4, -2), (4, 0))
    b.grid("P", (4, -2), (4, 0), (5, -1), (5, -3))


@figure("kneeling_man", "Man kneeling")
def _kneeling_man(b: Build) -> None:
    _profile(b)
    b.grid("S", (2, 2), (2, 4), (1, 3))
    b.grid("S", (0, 1), (0, 3), (-1, 2))
    b.grid("P", (0, -2), (0, 0), (1, 1), (1, -1))
    b.grid("M", (0, -2), (0, 0), (-2, -2))
    b.grid("L", (-2, -2), (-6, -2), (-4, 0))


@figure("praying_man", "Man praying")
def _praying_man(b: Build) -> None:
    _profile(b)
    b.grid("S", (2, 2), (2, 4), (1, 3))
    b.grid("S", (1, 1), (2, 2), (2, 0))
    b.grid("P", (0, -2), (0, 0), (1, 1), (1, -1))
    b.grid("M", (0, -3), (0, -1), (-2, -3))
    b.grid("L", (-2, -3), (-2, 1), (-4, -1))


# --------------------------------------------------------------------------- main


def build_all(ps: PieceSet | None = None, only: set[str] | None = None, check: bool = True) -> list[Figure]:
    """Build and check the registered figures (all, or the ids in ``only``), in registration order.

    With ``check`` False a figure that fails its checks is reported and kept (drafting).
    """
    ps = ps or tangram7()
    figs = []
    for fid, name, draw, turn in FIGURES:
        if only is not None and fid not in only:
            continue
        try:
            figs.append(make_figure(ps, fid, name, draw, turn))
        except (LibraryError, ValueError) as e:
            if check:
                raise
            print(f"!! {fid}: {e}")
            try:
                figs.append(make_figure(ps, fid, name, draw, turn, check=False))
            except ValueError:
                pass
    ids = [f.id for f in figs]
    names = [f.name for f in figs]
    if len(set(ids)) != len(ids) or len(set(names)) != len(names):
        raise LibraryError("figure ids and names must be unique")
    return figs


LIBRARY_NAME = "mrchaos-library"
LIBRARY_DESCRIPTION = (
    "Classic tangram figures authored for mrchaos by tools/author_library.py; "
    "families follow the perimeter rule (mrchaos.figures.families)."
)


def write_library(figs: list[Figure], path: str | Path) -> None:
    """Write the figures as interchange JSON, vertices in millimetres to the nanometre.

    :func:`mrchaos.figures.formats.save_figures` stores metres rounded to the micrometre.
    The loader re-fits every piece's pose to the rounded corners, so pieces that touch
    exactly come back up to ~0.5 um apart or into each other: overlaps of up to
    7e-8 m^2 and, where a shared edge runs through pixel centres (the rasteriser
    breaks such ties only to 1e-4 px = 0.2 um), empty pixels inside the silhouette.
    The format's ``units`` field allows millimetres, which keeps 1 nm. Entries are
    otherwise exactly what ``save_figures`` writes.
    """
    from mrchaos.core.atomic import write_atomic
    from mrchaos.figures.formats import figure_to_dict

    ps = figs[0].piece_set
    entries = []
    for f in figs:
        entry = figure_to_dict(f)
        for i, piece in enumerate(entry["pieces"]):
            # + 0.0 turns -0.0 into 0.0
            piece["vertices"] = (np.round(f.piece_polygon(i) * 1e3, 6) + 0.0).tolist()
        entries.append(entry)
    data = {
        "name": LIBRARY_NAME,
        "description": LIBRARY_DESCRIPTION,
        "units": "millimetre",
        "piece_set": ps.name,
        "piece_order": list(ps.names),
        "figures": entries,
    }
    write_atomic(path, json.dumps(data, indent=1) + "\n")
    # write_atomic keeps mkstemp's owner-only mode; package data should be readable by all
    Path(path).chmod(0o644)


def check_stored(path: str | Path, built: list[Figure], rule: FamilyRule = FamilyRule()) -> None:
    """Reload the written library and check it against the exact figures it came from."""
    from mrchaos.core.raster import View
    from mrchaos.figures.formats import load_json

    fs = load_json(path)
    if fs.rejected:
        raise LibraryError(f"{path}: the loader rejects {fs.rejected}")
    if fs.name != LIBRARY_NAME or [f.id for f in fs.figures] != [f.id for f in built]:
        raise LibraryError(f"{path}: name or figure ids differ from the authored ones")
    for stored, exact in zip(fs.figures, built, strict=True):
        where = f"{path}: figure {stored.id!r}"
        if stored.has_mirrored:
            raise LibraryError(f"{where}: stored with a flipped parallelogram")
        overlap = stored.overlap_area()
        if overlap >= OVERLAP_TOL:
            raise LibraryError(f"{where}: pieces overlap by {overlap:.2e} m^2 after reloading")
        shift = max(
            float(np.abs(stored.piece_polygon(i) - exact.piece_polygon(i)).max()) for i in range(len(exact.piece_set))
        )
        if shift > 1e-8:
            raise LibraryError(f"{where}: stored pieces moved {shift * 1e9:.0f} nm from the authored ones")
        for view in (View(), rule.view):
            if not bool((stored.silhouette(view) == exact.silhouette(view)).all()):
                raise LibraryError(f"{where}: the reloaded silhouette differs on the {view.extent} m view")


def main(argv: list[str] | None = None) -> int:
    """Build, check and report the library; write the JSON (and optionally a contact sheet)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=str(LIBRARY_PATH), help="library JSON to write")
    parser.add_argument("--sheet", default=None, help="also write a contact sheet PNG here")
    parser.add_argument("--only", default=None, help="comma-separated ids: build and draw only these (no JSON)")
    parser.add_argument("--tile", type=int, default=200, help="contact-sheet tile size (pixels)")
    parser.add_argument("--columns", type=int, default=8, help="contact-sheet columns")
    parser.add_argument("--draft", action="store_true", help="report broken figures instead of stopping (no JSON)")
    args = parser.parse_args(argv)

    only = set(args.only.split(",")) if args.only else None
    figs = build_all(only=only, check=not args.draft)
    rule = FamilyRule()
    counts: dict[str, int] = {}
    for f in figs:
        fam = family_of(f, rule)
        counts[fam] = counts.get(fam, 0) + 1
        edge, point = contacts(f)
        print(
            f"{f.id:15s} {f.name:20s} {fam:11s} {perimeter_px(f, rule):6.1f} px  "
            f"contacts: {len(edge)} edge, {len(point)} point"
        )
        if args.draft:
            shared = shared_boundary_mm(f)
            print(f"    shared {sum(shared.values()):.0f} mm:", shared, "points:", point)
    print("families:", ", ".join(f"{k} {v}" for k, v in sorted(counts.items())), f"(total {len(figs)})")
    if args.sheet:
        from mrchaos.figures.sheet import figure_sheet, save_png

        labelled = [
            Figure(f.id, f.piece_set, f.poses, f.mirrored, name=f.name, family=family_of(f, rule)) for f in figs
        ]
        save_png(figure_sheet(labelled, columns=args.columns, tile=args.tile), args.sheet)
        print("sheet:", args.sheet)
    if not (args.only or args.draft):
        write_library(figs, args.out)
        check_stored(args.out, figs, rule)
        print("wrote", args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
