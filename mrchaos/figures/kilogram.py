"""Import of KILOGRAM tangram SVGs (figures digitised from classic tangram books).

Each file holds seven ``<polygon>`` elements in no fixed piece order, at an
arbitrary scale, possibly with ``transform`` attributes, and with SVG's y axis
pointing down. The importer applies the transforms, flips y, scales the figure so
its pieces cover the 0.01 m^2 of the 100 mm tangram, centres it, identifies each
piece by its area and corner angles, and recovers its pose.
"""

from __future__ import annotations

import math
import re
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from mrchaos.core.geometry import fit_pose, polygon_area, rigid_transform
from mrchaos.figures.figure import Figure, FigureError, FigureSet
from mrchaos.figures.pieces import PieceSet, get_piece_set

__all__ = ["parse_svg_polygons", "svg_to_figure", "load_kilogram"]

_NUM = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")
_TRANSFORM = re.compile(r"(matrix|translate|scale|rotate|skewX|skewY)\s*\(([^)]*)\)")


def _transform_matrix(text: str | None, where: str) -> np.ndarray:
    """3x3 affine matrix of an SVG transform list (applied right to left, as SVG does)."""
    m = np.eye(3)
    if not text:
        return m
    for kind, args in _TRANSFORM.findall(text):
        v = [float(x) for x in _NUM.findall(args)]
        if kind == "matrix" and len(v) == 6:
            t = np.array([[v[0], v[2], v[4]], [v[1], v[3], v[5]], [0, 0, 1]])
        elif kind == "translate" and len(v) in (1, 2):
            t = np.array([[1, 0, v[0]], [0, 1, v[1] if len(v) == 2 else 0.0], [0, 0, 1]])
        elif kind == "scale" and len(v) in (1, 2):
            t = np.diag([v[0], v[1] if len(v) == 2 else v[0], 1.0])
        elif kind == "rotate" and len(v) in (1, 3):
            a = math.radians(v[0])
            r = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
            if len(v) == 3:
                tr = np.array([[1, 0, v[1]], [0, 1, v[2]], [0, 0, 1]])
                back = np.array([[1, 0, -v[1]], [0, 1, -v[2]], [0, 0, 1]])
                r = tr @ r @ back
            t = r
        elif kind in ("skewX", "skewY") and len(v) == 1:
            k = math.tan(math.radians(v[0]))
            t = (
                np.array([[1, k, 0], [0, 1, 0], [0, 0, 1]])
                if kind == "skewX"
                else np.array([[1, 0, 0], [k, 1, 0], [0, 0, 1]])
            )
        else:
            raise FigureError(f"{where}: cannot read transform {kind}({args})")
        m = m @ t
    return m


def _local(tag: str) -> str:
    return tag.rsplit("}", 1)[-1]


def parse_svg_polygons(path: str | Path) -> list[np.ndarray]:
    """All ``<polygon>`` outlines of an SVG in document coordinates (transforms applied, y down)."""
    where = str(path)
    try:
        root = ET.parse(path).getroot()
    except FileNotFoundError:
        raise FigureError(f"{where}: no such file") from None
    except ET.ParseError as e:
        raise FigureError(f"{where}: malformed SVG ({e})") from None
    out: list[np.ndarray] = []

    def walk(node: ET.Element, parent: np.ndarray) -> None:
        m = parent @ _transform_matrix(node.get("transform"), where)
        if _local(node.tag) == "polygon":
            nums = [float(x) for x in _NUM.findall(node.get("points", ""))]
            if len(nums) < 6 or len(nums) % 2:
                raise FigureError(f"{where}: polygon {node.get('id', '?')} has malformed points")
            pts = np.array(nums).reshape(-1, 2)
            pts = (m @ np.c_[pts, np.ones(len(pts))].T).T[:, :2]
            out.append(pts)
        for child in node:
            walk(child, m)

    walk(root, np.eye(3))
    return out


def _simplify(poly: np.ndarray, tol: float) -> np.ndarray:
    """Drop a repeated closing vertex, coincident vertices and vertices on a straight line."""
    pts = [p for i, p in enumerate(poly) if np.linalg.norm(p - poly[i - 1]) > tol]
    changed = True
    while changed and len(pts) > 3:
        changed = False
        for i in range(len(pts)):
            a, b, c = pts[i - 1], pts[i], pts[(i + 1) % len(pts)]
            cross = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
            if abs(cross) <= tol * np.linalg.norm(c - a):
                del pts[i]
                changed = True
                break
    return np.array(pts)


def _right_angled(poly: np.ndarray, tol_deg: float = 8.0) -> bool:
    a = np.roll(poly, 1, axis=0) - poly
    b = np.roll(poly, -1, axis=0) - poly
    cos = (a * b).sum(1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
    return bool(np.all(np.abs(np.degrees(np.arccos(np.clip(cos, -1, 1))) - 90) < tol_deg))


def _identify(ps: PieceSet, polys: list[np.ndarray], areas: np.ndarray, where: str) -> list[int]:
    """Polygon index for each piece id: shapes by corner count and right corners, sizes by area rank.

    Ranking (instead of matching absolute area fractions) tolerates the hand
    digitisation of the books, where a piece can be off by 10-20 % in area.
    """

    def kind(poly: np.ndarray) -> tuple[int, bool]:
        return len(poly), len(poly) == 4 and _right_angled(poly)

    piece_kind = [kind(p.outline) for p in ps.pieces]
    poly_kind = [kind(q) for q in polys]
    result = [-1] * len(ps)
    for k in sorted(set(piece_kind)):
        pieces = sorted((i for i, pk in enumerate(piece_kind) if pk == k), key=lambda i: -ps.pieces[i].area)
        cands = sorted((j for j, qk in enumerate(poly_kind) if qk == k), key=lambda j: (-areas[j], j))
        if len(cands) != len(pieces):
            what = f"{k[0]}-corner polygons" + (" with right corners" if k[1] else "")
            raise FigureError(f"{where}: not a standard tangram: {len(cands)} {what}, expected {len(pieces)}")
        for i, j in zip(pieces, cands, strict=True):  # twins (equal areas) keep file order
            result[i] = j
    return result


def svg_to_figure(
    path: str | Path, piece_set: PieceSet | None = None, fig_id: str | None = None, max_error: float = 8e-3
) -> Figure:
    """Import one KILOGRAM SVG as a figure.

    Pieces are identified, the figure is scaled to the tangram by the median of the
    per-piece scale estimates (robust to one badly digitised piece) and centred on
    its bounding box, and each exact piece is fitted to its polygon. The largest
    distance between a fitted and a source vertex goes to ``figure.meta['fit_error_m']``
    (per piece); a piece further off than ``max_error`` metres, or a file that is
    not seven tangram pieces, raises :class:`FigureError` with the reason.
    """
    ps = piece_set or get_piece_set("tangram7")
    fig_id = fig_id or Path(path).stem
    where = f"{path}: figure {fig_id!r}"
    raw = parse_svg_polygons(path)
    if len(raw) != len(ps):
        raise FigureError(f"{where}: not a standard tangram: {len(raw)} polygons, expected {len(ps)}")
    polys = [p * np.array([1.0, -1.0]) for p in raw]  # SVG's y points down
    areas = np.array([abs(polygon_area(p)) for p in polys])
    if not np.isfinite(areas).all() or not np.all(areas > 0):
        raise FigureError(f"{where}: degenerate or non-finite polygon")
    unit = math.sqrt(areas.sum() / ps.total_area)
    polys = [_simplify(p / unit, 2e-4) for p in polys]
    order = _identify(ps, polys, areas, where)
    est = [math.sqrt(abs(polygon_area(polys[j])) / ps.pieces[i].area) for i, j in enumerate(order)]
    scale = float(np.median(est))
    ordered = [polys[j] / scale for j in order]
    lo = np.min([p.min(0) for p in ordered], axis=0)
    hi = np.max([p.max(0) for p in ordered], axis=0)
    ordered = [p - (lo + hi) / 2 for p in ordered]

    poses = np.zeros((len(ps), 3))
    mirrored = np.zeros(len(ps), dtype=bool)
    errors = np.zeros(len(ps))
    for i, (piece, poly) in enumerate(zip(ps.pieces, ordered, strict=True)):
        fit = fit_pose(piece.outline, poly, piece.mirrored_outline() if piece.chiral else None)
        poses[i], mirrored[i] = fit.pose, fit.mirrored
        rebuilt = rigid_transform(piece.mirrored_outline() if fit.mirrored else piece.outline, fit.pose)
        errors[i] = np.linalg.norm(rebuilt[:, None] - poly[None], axis=-1).min(1).max()
        if errors[i] > max_error:
            raise FigureError(
                f"{where}: piece {piece.name} is {errors[i] * 1e3:.1f} mm from any exact {piece.name} "
                f"(limit {max_error * 1e3:.1f} mm): not a standard tangram"
            )
    meta = {"fit_error_m": errors.tolist(), "normalised_polygons": [p.tolist() for p in ordered]}
    return Figure(fig_id, ps, poses, mirrored, name=fig_id, source=str(path), meta=meta)


def load_kilogram(path: str | Path, validate: bool = True, piece_set: PieceSet | None = None) -> FigureSet:
    """Import one SVG or every ``*.svg`` of a folder; files that fail are listed as rejected."""
    p = Path(path)
    if p.is_dir():
        files = sorted(p.glob("*.svg"))
        if not files:
            raise FigureError(f"{p}: folder holds no .svg files")
    elif p.exists():
        files = [p]
    else:
        raise FigureError(f"{p}: no such file or folder")
    out = FigureSet(p.stem, [], source=str(p))
    for f in files:
        try:
            fig = svg_to_figure(f, piece_set)
            if validate:
                fig.validate()
            out.figures.append(fig)
        except FigureError as e:
            out.rejected.append((f.stem, str(e)))
    return out
