"""Chaos objects: random target assemblies, the only thing the policy trains on.

Three generators: two as in MRChaos, and one that joins pieces edge to edge as people do:

* ``scatter``: every piece at a uniformly random pose, no two overlapping, all
  inside the camera view (rejection sampling, vectorised over the batch);
* ``attract``: a scatter, then every piece is pulled toward one point until it
  touches the others, giving compact, touching, non-overlapping clusters. The pull
  is a kinematic relaxation: a piece moves toward the point (or slides along the
  axes when blocked) only if the move keeps it clear of every other piece, and the
  step halves when nothing can move, down to ``contact_gap``;
* ``tile``: pieces laid edge on edge, vertex on vertex, at the grid's angles, grown piece by
  piece (:mod:`mrchaos.tasks.tiling`).

A :class:`ChaosCache` stores pre-generated objects so a training run draws them
instead of paying the generation cost every episode.
"""

from __future__ import annotations

import io
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mrchaos.core.geometry import convex_penetration, rigid_transform, step_angles
from mrchaos.core.raster import View
from mrchaos.figures.pieces import PieceSet
from mrchaos.tasks.tiling import TileKnobs, tile_objects

__all__ = ["ChaosConfig", "scatter", "attract", "tile", "generate", "ChaosCache", "MODES"]

#: The generators, by the mode index a cache stores.
MODES = ("scatter", "attract", "tile")


@dataclass(frozen=True)
class ChaosConfig:
    """How random objects are drawn.

    Attributes:
        mode: "scatter", "attract", "tile" or "mix" (each object attract with
            ``attract_fraction``, tile with ``tile_fraction``, scatter otherwise).
        attract_fraction: share of attract objects under "mix" (the paper uses half).
        tile_fraction: share of tile (edge-joined) objects under "mix"; with
            ``attract_fraction`` at most 1.
        workspace: piece centroids are drawn in [-workspace, workspace]^2 (m).
        margin: every vertex stays this far (m) inside the camera view, so the whole object is seen.
        angle_step: rotations are multiples of this (rad); 0 draws continuous angles.
            The default matches the action grid's 45 degrees.
        contact_gap: the attraction stops when no piece can move this far (m).
        max_tries: rejection-sampling rounds per piece before giving up.
        mirror_prob: chance that a chiral piece lies turned over (its mirror image), so that a
            policy with a flip must read the face from the silhouette; 0 keeps every piece face up.
        tile_compactness: ``tile`` objects draw their compactness in [0, this]: how strongly a
            piece prefers the joint that shares the most outline (0: any joint alike).
        tile_limbs: ``tile`` objects draw their limb share in [0, this]: the chance that a piece
            after the second joins by the least outline, or vertex on vertex.
        tile_hole_prob: chance that a ``tile`` object may enclose empty regions.
    """

    mode: str = "mix"
    attract_fraction: float = 0.5
    workspace: float = 0.10
    margin: float = 0.005
    angle_step: float = math.pi / 4
    contact_gap: float = 2e-4
    max_tries: int = 200
    mirror_prob: float = 0.0
    tile_fraction: float = 0.0
    tile_compactness: float = 6.0
    tile_limbs: float = 0.3
    tile_hole_prob: float = 0.2

    def __post_init__(self) -> None:
        if self.mode not in MODES + ("mix",):
            raise ValueError(f"chaos mode must be one of {MODES + ('mix',)}, got {self.mode!r}")
        for name in ("attract_fraction", "tile_fraction", "mirror_prob", "tile_limbs", "tile_hole_prob"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"task.chaos.{name} must be in [0, 1], got {getattr(self, name)}")
        if self.attract_fraction + self.tile_fraction > 1.0 + 1e-12:
            raise ValueError(
                f"task.chaos.attract_fraction + tile_fraction must be at most 1, got "
                f"{self.attract_fraction} + {self.tile_fraction}"
            )
        if self.tile_compactness < 0:
            raise ValueError(f"task.chaos.tile_compactness must be >= 0, got {self.tile_compactness}")

    def shares(self) -> np.ndarray:
        """(3,) the share of objects each generator of :data:`MODES` draws."""
        if self.mode in MODES:
            return np.eye(len(MODES))[MODES.index(self.mode)]
        return np.array([1.0 - self.attract_fraction - self.tile_fraction, self.attract_fraction, self.tile_fraction])

    def bound(self, view: View) -> float:
        """Largest |x| or |y| (m) a vertex may reach in ``view``."""
        return view.extent / 2 - self.margin


def _draw_angles(rng: np.random.Generator, shape: tuple[int, ...], step: float) -> np.ndarray:
    if step <= 0:
        return rng.uniform(-math.pi, math.pi, shape)
    angles = step_angles(step)
    return angles[rng.integers(0, len(angles), shape)]


def scatter(
    piece_set: PieceSet,
    n: int,
    rng: np.random.Generator,
    cfg: ChaosConfig = ChaosConfig(),
    view: View = View(),
    mirrored: np.ndarray | None = None,
) -> np.ndarray:
    """(n, P, 3) poses: pieces at uniformly random poses, non-overlapping, inside the view;
    ``mirrored`` (n, P) bool: pieces that lie turned over."""
    parts = _object_parts(piece_set, n, mirrored)  # (n, P, K, V, 2)
    p = len(piece_set)
    poses = np.zeros((n, p, 3))
    polys = np.zeros(parts.shape)
    bound = cfg.bound(view)
    for k in range(p):
        todo = np.arange(n)
        for _ in range(cfg.max_tries):
            m = len(todo)
            cand = np.concatenate(
                [rng.uniform(-cfg.workspace, cfg.workspace, (m, 2)), _draw_angles(rng, (m, 1), cfg.angle_step)], 1
            )
            poly = rigid_transform(parts[todo, k], cand[:, None])  # (m, K, V, 2)
            ok = np.abs(poly).max((1, 2, 3)) <= bound
            if k > 0:
                ok &= _clear(poly, polys[todo, :k])
            poses[todo[ok], k] = cand[ok]
            polys[todo[ok], k] = poly[ok]
            todo = todo[~ok]
            if len(todo) == 0:
                break
        if len(todo):
            raise RuntimeError(
                f"scatter: could not place {piece_set.names[k]} in {len(todo)} objects after "
                f"{cfg.max_tries} tries; enlarge the workspace"
            )
    return poses


def attract(
    piece_set: PieceSet,
    n: int,
    rng: np.random.Generator,
    cfg: ChaosConfig = ChaosConfig(),
    view: View = View(),
    start: np.ndarray | None = None,
    mirrored: np.ndarray | None = None,
) -> np.ndarray:
    """(n, P, 3) poses: a scatter pulled together into a touching cluster, then centred;
    ``mirrored`` (n, P) bool: pieces that lie turned over."""
    parts = _object_parts(piece_set, n, mirrored)
    p = len(piece_set)
    poses = scatter(piece_set, n, rng, cfg, view, mirrored) if start is None else np.array(start, dtype=np.float64)
    # The point of attraction: a random point near the centre, so clusters are not all alike.
    centre = rng.uniform(-0.02, 0.02, (n, 1, 2))
    step = np.full(n, 0.01)
    polys = rigid_transform(parts, poses[:, :, None])  # (n, P, K, V, 2)
    active = np.ones(n, dtype=bool)
    while active.any():
        moved = np.zeros(n, dtype=bool)
        for k in rng.permutation(p):
            rows = np.flatnonzero(active)
            to = centre[rows, 0] - poses[rows, k, :2]
            dist = np.linalg.norm(to, axis=1)
            unit = to / np.maximum(dist, 1e-12)[:, None]
            s = np.minimum(step[rows], dist)
            others = np.delete(polys[rows], k, axis=1)
            done = np.zeros(len(rows), dtype=bool)
            progress = np.zeros(len(rows))
            # Straight toward the point, else slide along x, else along y.
            for direction in (unit, unit * [1.0, 0.0], unit * [0.0, 1.0]):
                d = direction * s[:, None]
                cand = polys[rows, k] + d[:, None, None, :]
                ok = ~done & (np.linalg.norm(d, axis=1) > 1e-9)
                ok &= _clear(cand, others)
                r = rows[ok]
                poses[r, k, :2] += d[ok]
                polys[r, k] = cand[ok]
                progress[ok] = dist[ok] - np.linalg.norm(centre[r, 0] - poses[r, k, :2], axis=1)
                done |= ok
            # Only real progress keeps the step: tiny slides back and forth must not stall the halving.
            moved[rows[progress > 0.25 * step[rows]]] = True
        stuck = active & ~moved
        step[stuck] /= 2
        active &= step >= cfg.contact_gap
    # Centre each cluster on its bounding box.
    lo, hi = polys.min((1, 2, 3)), polys.max((1, 2, 3))
    poses[..., :2] -= ((lo + hi) / 2)[:, None, :]
    return poses


def tile(
    piece_set: PieceSet,
    n: int,
    rng: np.random.Generator,
    cfg: ChaosConfig = ChaosConfig(),
    view: View = View(),
    mirrored: np.ndarray | None = None,
) -> np.ndarray:
    """(n, P, 3) poses: pieces laid edge on edge at the grid's angles, grown piece by piece
    (:mod:`mrchaos.tasks.tiling`), centred, inside the view; ``mirrored`` (n, P) bool."""
    knobs = TileKnobs(cfg.tile_compactness, cfg.tile_limbs, cfg.tile_hole_prob)
    return tile_objects(piece_set, n, rng, knobs, cfg.angle_step, 2 * cfg.bound(view), cfg.max_tries, mirrored)


def _object_parts(piece_set: PieceSet, n: int, mirrored: np.ndarray | None) -> np.ndarray:
    """(n, P, K, V, 2) convex parts of every piece of n objects, mirrored where ``mirrored`` (n, P)."""
    p, k = len(piece_set), piece_set.parts_per_piece
    parts = piece_set.padded_parts()
    parts = np.broadcast_to(parts.reshape(p, k, *parts.shape[1:]), (n, p, k, *parts.shape[1:]))
    if mirrored is None or not np.any(mirrored):
        return parts
    turned = piece_set.padded_parts(np.ones(p, dtype=bool)).reshape(p, k, *parts.shape[3:])
    return np.where(np.asarray(mirrored)[:, :, None, None, None], turned[None], parts)


def _clear(poly: np.ndarray, others: np.ndarray) -> np.ndarray:
    """(m,) True where parts ``poly`` (m, K, V, 2) overlap none of ``others`` (m, j, K, V, 2)."""
    depth = convex_penetration(poly[:, None, :, None], others[:, :, None])  # (m, j, K, K)
    return np.asarray((depth <= 0).all((1, 2, 3)))


def generate(
    piece_set: PieceSet, n: int, rng: np.random.Generator, cfg: ChaosConfig = ChaosConfig(), view: View = View()
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(n, P, 3) poses, (n,) int8 mode index (into :data:`MODES`) and (n, P) bool mirrored
    (chiral pieces turned over), drawn as ``cfg`` says, inside ``view``."""
    if cfg.mode in MODES:
        modes = np.full(n, MODES.index(cfg.mode), dtype=np.int8)
    else:
        # One uniform per object: with no tile share, the draw is the same as before tile existed.
        u = rng.random(n)
        modes = np.where(u < cfg.attract_fraction, 1, np.where(u < cfg.attract_fraction + cfg.tile_fraction, 2, 0))
        modes = modes.astype(np.int8)
    mirrored = np.zeros((n, len(piece_set)), dtype=bool)
    if cfg.mirror_prob > 0:  # no draw otherwise, so that objects without mirroring stay as they were
        mirrored = (rng.random((n, len(piece_set))) < cfg.mirror_prob) & piece_set.chiral
    poses = np.zeros((n, len(piece_set), 3))
    generators: tuple[Callable[..., np.ndarray], ...] = (scatter, attract, tile)
    for m, fn in enumerate(generators):
        idx = np.flatnonzero(modes == m)
        if len(idx):
            poses[idx] = fn(piece_set, len(idx), rng, cfg, view, mirrored=mirrored[idx])
    return poses, modes, mirrored


class ChaosCache:
    """Pre-generated chaos objects of one piece set, saved as ``.npz``.

    Args:
        poses: (N, P, 3) target poses.
        modes: (N,) generator index per object, into :data:`MODES`.
        piece_set: name of the piece set the poses belong to.
        mirrored: (N, P) bool, pieces lying turned over (default: none; caches written before
            the flip have no such array).
    """

    def __init__(
        self, poses: np.ndarray, modes: np.ndarray, piece_set: str, mirrored: np.ndarray | None = None
    ) -> None:
        self.poses = np.asarray(poses, dtype=np.float64)
        self.modes = np.asarray(modes, dtype=np.int8)
        self.piece_set = piece_set
        self.mirrored = (
            np.zeros(self.poses.shape[:2], dtype=bool) if mirrored is None else np.asarray(mirrored, dtype=bool)
        )
        if (
            self.poses.ndim != 3
            or self.poses.shape[-1] != 3
            or len(self.modes) != len(self.poses)
            or self.mirrored.shape != self.poses.shape[:2]
        ):
            raise ValueError(
                f"chaos cache: inconsistent shapes {self.poses.shape} / {self.modes.shape} / {self.mirrored.shape}"
            )

    def __len__(self) -> int:
        return len(self.poses)

    @classmethod
    def build(
        cls, piece_set: PieceSet, n: int, seed: int, cfg: ChaosConfig = ChaosConfig(), view: View = View()
    ) -> ChaosCache:
        """Generate ``n`` objects with a seeded generator."""
        poses, modes, mirrored = generate(piece_set, n, np.random.default_rng(seed), cfg, view)
        return cls(poses, modes, piece_set.name, mirrored)

    def save(self, path: str | Path) -> None:
        """Write atomically."""
        from mrchaos.core.atomic import write_atomic

        buf = io.BytesIO()
        np.savez_compressed(
            buf, poses=self.poses.astype(np.float32), modes=self.modes, piece_set=self.piece_set, mirrored=self.mirrored
        )
        write_atomic(path, buf.getvalue())

    @classmethod
    def load(cls, path: str | Path, piece_set: PieceSet | None = None) -> ChaosCache:
        """Read a cache; a corrupt file or another piece set's cache raises ValueError naming the file."""
        try:
            with np.load(path, allow_pickle=False) as z:
                cache = cls(z["poses"], z["modes"], str(z["piece_set"]), z["mirrored"] if "mirrored" in z else None)
        except FileNotFoundError:
            raise ValueError(f"{path}: no such chaos cache") from None
        except (OSError, KeyError, ValueError) as e:
            raise ValueError(f"{path}: not a valid chaos cache ({e})") from None
        if piece_set is not None and (cache.piece_set != piece_set.name or cache.poses.shape[1] != len(piece_set)):
            raise ValueError(f"{path}: cache is for piece set {cache.piece_set!r}, not {piece_set.name!r}")
        return cache

    def sample(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """(n, P, 3) poses and (n, P) mirrored flags of objects drawn uniformly with replacement."""
        i = rng.integers(0, len(self), n)
        return self.poses[i], self.mirrored[i]
