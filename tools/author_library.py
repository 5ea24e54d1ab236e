"""Author the built-in library of human-designed tangram figures.

Run ``python tools/author_library.py`` to rebuild ``mrchaos/data/library.json``
deterministically; ``--sheet PATH.png`` also writes a contact sheet to look at.

Every figure is written in a small placement language (see :class:`Build`):
pieces are placed by a vertex and edge directions in multiples of 45 degrees,
and new pieces are anchored on vertices of pieces already placed or on points
along their edges. Coordinates are therefore exact (computed, never typed as
decimals), pieces meet flush as in tangram books, and the checks below can
demand zero overlap rather than a tolerance.

Lengths inside the language are millimetres of the 100 mm tangram:

* ``A`` = 35.36 mm: small-triangle leg, square side, parallelogram short side;
* ``B`` = 50 mm: medium-triangle leg, small-triangle hypotenuse, parallelogram long side;
* ``C`` = 70.71 mm: large-triangle leg, medium-triangle hypotenuse;
* ``D`` = 100 mm: large-triangle hypotenuse.

A figure may be authored with either handedness of the parallelogram; when
the recovered pose says the piece is flipped, the whole figure is reflected
(x -> -x), because a suction robot cannot turn the piece over.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import shapely
from shapely.ops import unary_union

from mrchaos.families import FamilyRule, family_of, silhouette_perimeter_px
from mrchaos.figure import Figure, figure_from_polygons
from mrchaos.figure_io import save_figures
from mrchaos.pieces import PieceSet, tangram7

A = 100.0 / (2.0 * math.sqrt(2.0))
B = 50.0
C = 2.0 * A
D = 100.0

#: Largest |coordinate| a centred figure may reach (m): leaves margin in the 0.26 m view.
MAX_REACH = 0.115
#: Pieces closer than this (m) touch.
TOUCH_TOL = 1e-7
#: Largest pairwise overlap (m^2) a figure may have; exact placement gives ~1e-12.
OVERLAP_TOL = 1e-8
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


def lerp(p: Point, q: Point, t: float) -> Point:
    """The point a fraction ``t`` of the way from p to q."""
    return np.asarray(p) + t * (np.asarray(q) - np.asarray(p))


def toward(p: Point, q: Point, length: float) -> Point:
    """The point ``length`` mm from p in the direction of q (a point along an edge)."""
    p, q = np.asarray(p), np.asarray(q)
    d = q - p
    return p + d * (length / float(np.hypot(*d)))


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
            # both ends of q's edge on the line through p's edge
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
    # union-find over the contact graph: the pieces must form one connected shape
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
    # a piece hanging on by a single point is allowed (the books do it), a figure held
    # together mostly by points is not: it would not read as one shape
    if len(point) > len(edge):
        raise LibraryError(f"{where}: {len(point)} point contacts but only {len(edge)} edge contacts")
    union = unary_union([shapely.Polygon(fig.piece_polygon(i)) for i in range(n)])
    if abs(union.area - fig.piece_set.total_area) > 1e-9:
        raise LibraryError(f"{where}: union area {union.area * 1e6:.1f} mm^2 != total piece area")
    fig.validate()


# --------------------------------------------------------------------------- building


def make_figure(ps: PieceSet, fig_id: str, name: str, draw: Callable[[Build], None], check: bool = True) -> Figure:
    """Run a figure's drawing function and turn the result into a centred, unflipped figure.

    With ``check`` False a broken figure is returned anyway (for drawing while authoring).
    """
    b = Build()
    draw(b)
    polys = b.polygons()
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


FIGURES: list[tuple[str, str, Callable[[Build], None]]] = []


def figure(fig_id: str, name: str) -> Callable[[Callable[[Build], None]], Callable[[Build], None]]:
    """Register a drawing function as library figure ``fig_id`` called ``name``."""

    def register(draw: Callable[[Build], None]) -> Callable[[Build], None]:
        FIGURES.append((fig_id, name, draw))
        return draw

    return register


def perimeter_px(fig: Figure, rule: FamilyRule = FamilyRule()) -> float:
    """The silhouette perimeter the family rule sees (pixels)."""
    return silhouette_perimeter_px(fig.silhouette(rule.view).numpy())


# --------------------------------------------------------------------------- figures


@figure("square", "Square")
def _square(b: Build) -> None:
    b.hyp("L", pt(0, 0), 0)
    b.hyp("L", pt(0, D), -90)
    b.tri("M", pt(D, D), 180)
    b.hyp("S", pt(D, 0), 90)
    b.square(pt(B, B), -45)
    b.tri("S", pt(B, B), 45)
    b.para(pt(25, 75), 0, 135)


# --------------------------------------------------------------------------- main


def build_all(ps: PieceSet | None = None, only: set[str] | None = None, check: bool = True) -> list[Figure]:
    """Build and check the registered figures (all, or the ids in ``only``), in registration order."""
    ps = ps or tangram7()
    figs = []
    for fid, name, draw in FIGURES:
        if only is not None and fid not in only:
            continue
        try:
            figs.append(make_figure(ps, fid, name, draw, check=check))
        except (LibraryError, ValueError) as e:
            if check:
                raise
            print(f"{fid}: {e}", file=sys.stderr)
            try:
                figs.append(make_figure(ps, fid, name, draw, check=False))
            except ValueError:
                pass
    ids = [f.id for f in figs]
    names = [f.name for f in figs]
    if len(set(ids)) != len(ids) or len(set(names)) != len(names):
        raise LibraryError("figure ids and names must be unique")
    return figs


def main(argv: list[str] | None = None) -> int:
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
        print(f"{f.id:18s} {f.name:22s} {fam:11s} {perimeter_px(f, rule):6.1f} px  "
              f"contacts {len(edge)} edge {len(point)} point")
    print("families:", ", ".join(f"{k} {v}" for k, v in sorted(counts.items())), f"(total {len(figs)})")
    if args.sheet:
        from mrchaos.sheet import figure_sheet, save_png

        labelled = [Figure(f.id, f.piece_set, f.poses, f.mirrored, name=f.name, family=family_of(f, rule))
                    for f in figs]
        save_png(figure_sheet(labelled, columns=args.columns, tile=args.tile), args.sheet)
        print("sheet:", args.sheet)
    if not (args.only or args.draft):
        save_figures(figs, args.out, name="mrchaos-library",
                     description="Classic tangram figures authored for mrchaos by tools/author_library.py; "
                                 "families follow the perimeter rule (mrchaos.families).")
        print("wrote", args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
