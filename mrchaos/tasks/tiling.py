"""Edge-joined random objects (chaos mode ``tile``): pieces laid edge on edge, as people draw.

An attraction cluster touches at corners and slivers; the figures people draw are joined
edge to edge, vertex on vertex, at 45° to one another, mostly in one block. This generator
grows each object piece by piece in a random order. A new piece, at one of the grid's
orientations (turned over where the object's ``mirrored`` flag says), lays one of its edges
along an edge of a piece already down, facing it, so that the two share a segment whose ends
fall on the edges' vertices or midpoints (the tangram's unit points: a small triangle at the
middle of a large triangle's leg, two hypotenuses end to end). Candidates that overlap a piece
or would not fit the camera view are dropped; one of the rest is drawn.

Each object draws its own knobs, so one cache spans compact blocks and figures with limbs:

* compactness ``kappa`` in [0, ``compactness``]: a candidate's weight is
  ``exp(kappa * contact / unit)``, where ``contact`` is all the outline it shares with the
  object and ``unit`` the set's shortest edge; 0 draws uniformly among the joints;
* limbs: each piece after the second joins as a limb with a probability drawn in
  [0, ``limbs``]: it prefers the least contact, and one limb in four meets the object
  vertex on vertex only (a head on a neck);
* holes: with probability ``hole_prob`` the object may enclose empty regions; otherwise
  a joint that closes a loop around an empty region is refused.

The generator reads no human figure.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import shapely

from mrchaos.core.geometry import convex_penetration, rigid_transform, step_angles
from mrchaos.figures.pieces import PieceSet

__all__ = ["TileKnobs", "tile_objects"]

#: Overlap (m) that still counts as touching: exact joints meet to rounding error only.
_TOUCH = 1e-7
#: Share of limb joints made vertex on vertex only (the rest share the least outline they can).
_CORNER_SHARE = 0.25
#: An enclosed region smaller than this (m^2) is a rounding artefact, not a hole.
_HOLE_AREA = 1e-6


@dataclass(frozen=True)
class TileKnobs:
    """The ranges each object draws its knobs from (``task.chaos.tile_*`` sets them).

    Attributes:
        compactness: the object's compactness is drawn in [0, this].
        limbs: the object's limb share is drawn in [0, this].
        hole_prob: chance that the object may enclose empty regions.
    """

    compactness: float
    limbs: float
    hole_prob: float


def tile_objects(
    piece_set: PieceSet,
    n: int,
    rng: np.random.Generator,
    knobs: TileKnobs,
    angle_step: float,
    span: float,
    max_tries: int,
    mirrored: np.ndarray | None = None,
) -> np.ndarray:
    """(n, P, 3) centroid poses of edge-joined objects, centred on their bounding boxes: pieces
    at multiples of ``angle_step`` (rad), each object within ``span`` m across in x and in y;
    ``mirrored`` (n, P) bool: pieces turned over. An object that finds no joint for a piece is
    drawn again, up to ``max_tries`` times."""
    if angle_step <= 0:
        raise ValueError("chaos mode 'tile' lays pieces at the grid's angles: task.chaos.angle_step must be > 0")
    p = len(piece_set)
    mirrored = np.zeros((n, p), dtype=bool) if mirrored is None else np.asarray(mirrored, dtype=bool)
    angles = step_angles(angle_step)
    shapes = {flip: _Shapes(piece_set, angles, flip) for flip in (False, True)}
    unit = _shortest_edge(piece_set)
    poses = np.zeros((n, p, 3))
    for b in range(n):
        for _ in range(max_tries):
            got = _grow(piece_set, rng, knobs, shapes, mirrored[b], span, unit)
            if got is not None:
                poses[b] = got
                break
        else:
            raise RuntimeError(f"tile: no edge-joined object of {piece_set.name} fits the view after {max_tries} tries")
    return poses


class _Shapes:
    """Every piece of a set at every grid angle: outline vertices, edges and convex parts."""

    def __init__(self, piece_set: PieceSet, angles: np.ndarray, flip: bool) -> None:
        self.angles = angles
        k = piece_set.parts_per_piece
        flags = piece_set.chiral & flip
        parts = piece_set.padded_parts(flags).reshape(len(piece_set), k, -1, 2)
        pose = np.zeros((len(angles), 3))
        pose[:, 2] = angles
        self.verts: list[np.ndarray] = []  # per piece (A, V, 2)
        self.parts: list[np.ndarray] = []  # per piece (A, K, Vmax, 2)
        for i, piece in enumerate(piece_set.pieces):
            outline = piece.mirrored_outline() if flip and piece.chiral else piece.outline
            self.verts.append(rigid_transform(outline, pose))
            self.parts.append(rigid_transform(parts[i], pose[:, None]))


class _Edges(NamedTuple):
    """A closed polygon's edges: start points (..., V, 2), unit directions (..., V, 2) (zero for a
    zero-length edge) and lengths (..., V)."""

    start: np.ndarray
    unit: np.ndarray
    length: np.ndarray


def _edges(verts: np.ndarray) -> _Edges:
    """The edges of polygons ``verts`` (..., V, 2)."""
    d = np.roll(verts, -1, axis=-2) - verts
    length = np.linalg.norm(d, axis=-1)
    return _Edges(verts, d / np.maximum(length, 1e-12)[..., None], length)


def _grow(
    piece_set: PieceSet,
    rng: np.random.Generator,
    knobs: TileKnobs,
    shapes: dict[bool, _Shapes],
    mirrored: np.ndarray,
    span: float,
    unit: float,
) -> np.ndarray | None:
    """One object's centroid poses, or None when a piece found no joint (the caller retries);
    ``unit`` (m) is the contact that counts as one in the compactness weight."""
    p = len(piece_set)
    kappa = rng.uniform(0.0, knobs.compactness)
    limb_share = rng.uniform(0.0, knobs.limbs)
    holes = rng.random() < knobs.hole_prob
    order = rng.permutation(p)
    poses = np.zeros((p, 3))
    placed_verts: list[np.ndarray] = []
    placed_parts: list[np.ndarray] = []
    for step, i in enumerate(order):
        sh = shapes[bool(mirrored[i] and piece_set.pieces[i].chiral)]
        if step == 0:
            a = int(rng.integers(len(sh.angles)))
            poses[i] = (0.0, 0.0, sh.angles[a])
            placed_verts.append(sh.verts[i][a])
            placed_parts.append(sh.parts[i][a])
            continue
        limb = step >= 2 and rng.random() < limb_share
        corner = limb and rng.random() < _CORNER_SHARE
        placed = _Edges(*(np.concatenate(x) for x in zip(*map(_edges, placed_verts), strict=True)))
        angle, shift = _candidates(sh.verts[i], placed, corners=corner)
        if len(angle) == 0:
            return None
        verts = sh.verts[i][angle] + shift[:, None]  # (C, V, 2)
        parts = sh.parts[i][angle] + shift[:, None, None]  # (C, K, Vmax, 2)
        # Inside the view once the object is centred: its box, with this piece, fits the span.
        lo = np.minimum(np.min([v.min(0) for v in placed_verts], 0), verts.min(1))
        hi = np.maximum(np.max([v.max(0) for v in placed_verts], 0), verts.max(1))
        ok = ((hi - lo) <= span).all(1)
        others = np.concatenate(placed_parts)  # (M, Vmax, 2)
        depth = convex_penetration(parts[:, :, None], others[None, None])  # (C, K, M)
        ok &= (depth <= _TOUCH).all((1, 2))
        contact = _contact(verts, placed)
        ok &= (contact > 0) | corner
        idx = np.flatnonzero(ok)
        if len(idx) == 0:
            return None
        score = (-1.0 if limb else 1.0) * kappa * contact[idx] / unit
        weight = np.exp(score - score.max())
        while len(idx):
            pick = rng.choice(len(idx), p=weight / weight.sum())
            c = idx[pick]
            if holes or not _encloses(placed_verts + [verts[c]]):
                break
            idx, weight = np.delete(idx, pick), np.delete(weight, pick)
        else:
            return None
        poses[i] = (shift[c, 0], shift[c, 1], sh.angles[angle[c]])
        placed_verts.append(verts[c])
        placed_parts.append(parts[c])
    allv = np.concatenate(placed_verts)
    poses[:, :2] -= (allv.min(0) + allv.max(0)) / 2
    return poses


def _shortest_edge(piece_set: PieceSet) -> float:
    """The set's shortest outline edge (m): the unit of contact in the compactness weight."""
    lengths = [_edges(q.outline).length for q in piece_set.pieces]
    return float(min(x[x > 1e-9].min() for x in lengths))


def _candidates(verts: np.ndarray, placed: _Edges, corners: bool) -> tuple[np.ndarray, np.ndarray]:
    """Joints of a piece (outline ``verts`` (A, V, 2) at each grid angle, centroid at the origin)
    to the placed edges (:func:`_edges` of every placed outline, concatenated): (C,) angle index
    and (C, 2) centroid position of each.

    An edge joint puts one of the piece's edges along a placed edge, facing it, with an end or
    the midpoint of one on an end or the midpoint of the other, sharing at least half the
    shorter edge. A corner joint (``corners``) puts one of its vertices on a placed vertex.
    """
    obj_a, u1, len1 = placed
    _, u2, len2 = _edges(verts)  # (A, V, 2)
    pb = np.roll(verts, -1, axis=-2)
    # Facing edges run antiparallel (both outlines counter-clockwise).
    facing = (np.einsum("avk,ek->eav", u2, u1) < -1 + 1e-9) & (len2 > 1e-9)[None] & (len1 > 1e-9)[:, None, None]
    e, a, v = np.nonzero(facing)
    angle_out, shift_out = [], []
    if len(e):
        l1, l2 = len1[e], len2[a, v]
        # The piece's edge covers [s, s + l2] along the placed edge (its end vertex at s).
        marks = np.array([0.0, 0.5, 1.0])
        s = (l1[:, None, None] * marks[:, None] - l2[:, None, None] * marks[None, :]).reshape(len(e), 9)
        shared = np.minimum(l1[:, None], s + l2[:, None]) - np.maximum(0.0, s)
        good = shared >= 0.5 * np.minimum(l1, l2)[:, None] - 1e-9
        row, col = np.nonzero(good)
        end = obj_a[e[row]] + s[row, col, None] * u1[e[row]]
        shift_out.append(end - pb[a[row], v[row]])
        angle_out.append(a[row])
    if corners:
        na, nv = verts.shape[:2]
        shift_out.append((obj_a[:, None, None] - verts[None]).reshape(-1, 2))
        angle_out.append(np.broadcast_to(np.arange(na)[None, :, None], (len(obj_a), na, nv)).reshape(-1))
    if not angle_out:
        return np.zeros(0, dtype=np.int64), np.zeros((0, 2))
    angle = np.concatenate(angle_out)
    shift = np.concatenate(shift_out)
    # The same joint is often reached from several marks: keep one of each.
    key = np.c_[angle, np.round(shift / 1e-7)]
    _, first = np.unique(key, axis=0, return_index=True)
    first = np.sort(first)
    return angle[first], shift[first]


def _contact(verts: np.ndarray, placed: _Edges) -> np.ndarray:
    """(C,) outline length (m) that each candidate (C, V, 2) shares with the placed edges
    (:func:`_edges`, concatenated): facing, collinear segments' overlap."""
    pa, u2, len2 = _edges(verts)
    qa, u1, len1 = placed
    dot = np.einsum("cvk,ek->cve", u2, u1)
    # Distance of the candidate edge's start from the placed edge's line.
    rel = pa[:, :, None] - qa[None, None]  # (C, V, E, 2)
    off = np.abs(rel[..., 0] * u1[:, 1] - rel[..., 1] * u1[:, 0])
    t0 = np.einsum("cvek,ek->cve", rel, u1)
    t1 = t0 + dot * len2[..., None]
    lo, hi = np.minimum(t0, t1), np.maximum(t0, t1)
    overlap = np.clip(np.minimum(hi, len1) - np.maximum(lo, 0.0), 0.0, None)
    real = (len2[..., None] > 1e-9) & (len1 > 1e-9)
    return np.where((dot < -1 + 1e-9) & (off < 1e-7) & real, overlap, 0.0).sum((1, 2))


def _encloses(outlines: list[np.ndarray]) -> bool:
    """True when the union of the outlines encloses an empty region larger than rounding."""
    pad = 1e-6  # closes the zero-width seams between joined pieces
    union = shapely.union_all([shapely.Polygon(v).buffer(pad, join_style="mitre") for v in outlines])
    polys = union.geoms if hasattr(union, "geoms") else [union]
    return any(shapely.Polygon(r).area > _HOLE_AREA for g in polys for r in g.interiors)
