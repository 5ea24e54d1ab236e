"""How the pieces of an assembly join: the outline each pair shares, and the blocks they form.

Human figures are joined edge to edge; chaos objects touch at corners and slivers. These
measures tell the two apart without a policy, for any assembly (a figure, a chaos object):

* ``touching``: the share of a piece's outline that lies along another piece;
* ``shared``: the outline length two pieces share;
* blocks: the groups of pieces linked by pairs that share at least ``block_edge`` of outline.

Outlines count as shared within ``tolerance`` of each other, so drawn figures, whose seams are
a fraction of a millimetre wide, and attraction clusters, which stop short of contact, are
measured alike.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import shapely

from mrchaos.figures.figure import Figure
from mrchaos.figures.pieces import PieceSet

__all__ = ["Joints", "assembly_joints", "JointSummary", "summarize_joints"]


@dataclass(frozen=True)
class Joints:
    """One assembly's joints.

    Attributes:
        shared: (P, P) outline length (m) each pair of pieces shares (symmetric, 0 diagonal).
        touching: (P,) share of each piece's outline that lies along another piece.
        perimeter: (P,) each piece's outline length (m).
        blocks: (P,) block label of each piece, 0 upwards.
    """

    shared: np.ndarray
    touching: np.ndarray
    perimeter: np.ndarray
    blocks: np.ndarray

    @property
    def touching_share(self) -> float:
        """The share of the assembly's whole outline (all pieces') that lies along another piece."""
        return float((self.touching * self.perimeter).sum() / self.perimeter.sum())

    @property
    def n_blocks(self) -> int:
        """How many blocks the assembly falls into."""
        return int(self.blocks.max()) + 1


def assembly_joints(
    piece_set: PieceSet,
    poses: np.ndarray,
    mirrored: np.ndarray | None = None,
    tolerance: float = 5e-4,
    block_edge: float = 5e-3,
) -> Joints:
    """The joints of one assembly: centroid poses (P, 3), ``mirrored`` (P,) bool; outlines within
    ``tolerance`` (m) count as shared; pairs sharing ``block_edge`` (m) or more join a block."""
    faces = np.zeros(len(piece_set), dtype=bool) if mirrored is None else mirrored
    assembly = Figure("assembly", piece_set, poses, faces)
    polys = [shapely.Polygon(assembly.piece_polygon(i)) for i in range(len(piece_set))]
    p = len(polys)
    grown = [q.buffer(tolerance, join_style="mitre") for q in polys]
    shared = np.zeros((p, p))
    touching = np.zeros(p)
    for i in range(p):
        near = [j for j in range(p) if j != i and polys[i].distance(polys[j]) <= tolerance]
        for j in near:
            shared[i, j] = polys[i].exterior.intersection(grown[j]).length
        if near:
            others = shapely.union_all([grown[j] for j in near])
            touching[i] = polys[i].exterior.intersection(others).length / polys[i].exterior.length
    # Each side measures its own outline; the pair shares what both see.
    shared = np.minimum(shared, shared.T)
    perimeter = np.array([q.exterior.length for q in polys])
    return Joints(shared, touching, perimeter, _components(shared >= block_edge))


def _components(linked: np.ndarray) -> np.ndarray:
    """(P,) component label, 0 upwards in order of first piece, of a symmetric (P, P) bool graph."""
    label = np.full(len(linked), -1)
    for start in range(len(linked)):
        if label[start] >= 0:
            continue
        stack, label[start] = [start], label.max() + 1
        while stack:
            i = stack.pop()
            for j in np.flatnonzero(linked[i] & (label < 0)):
                label[j] = label[start]
                stack.append(int(j))
    return label


@dataclass(frozen=True)
class JointSummary:
    """A set's joints, over its assemblies (the concepts page's table).

    Attributes:
        touching: the median assembly's share of outline that lies along another piece.
        edge_share: share of pieces that share at least ``edge`` (m) with one neighbour.
        blocks: the median number of blocks per assembly.
        one_block: share of assemblies that are one block.
        n: how many assemblies.
    """

    touching: float
    edge_share: float
    blocks: float
    one_block: float
    n: int


def summarize_joints(
    piece_set: PieceSet,
    poses: np.ndarray,
    mirrored: np.ndarray | None = None,
    edge: float = 0.025,
) -> JointSummary:
    """Summarise the joints of assemblies ``poses`` (N, P, 3), ``mirrored`` (N, P) bool."""
    poses = np.asarray(poses, dtype=np.float64)
    if len(poses) == 0:
        raise ValueError("summarize_joints: no assemblies")
    joints = [assembly_joints(piece_set, x, None if mirrored is None else mirrored[b]) for b, x in enumerate(poses)]
    touching = np.array([j.touching_share for j in joints])
    edged = np.concatenate([j.shared.max(1) >= edge for j in joints])
    blocks = np.array([j.n_blocks for j in joints])
    return JointSummary(
        touching=float(np.median(touching)),
        edge_share=float(edged.mean()),
        blocks=float(np.median(blocks)),
        one_block=float((blocks == 1).mean()),
        n=len(joints),
    )
