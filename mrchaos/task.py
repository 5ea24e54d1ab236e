"""The task sampler: where each episode's target comes from.

Targets are chaos objects (drawn fresh, or from a pre-generated cache) or
figures from figure sets, in a mix set by config. Everything is drawn from the
caller's generator, so a seeded environment gets the same targets every run.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mrchaos.chaos import ChaosCache, ChaosConfig, generate
from mrchaos.figure import Figure
from mrchaos.pieces import PieceSet

__all__ = ["TaskConfig", "TaskBatch", "TaskSampler", "SOURCES"]

log = logging.getLogger(__name__)

#: Target sources, by index.
SOURCES = ("chaos", "cache", "figures")


@dataclass
class TaskConfig:
    """Where targets come from.

    Attributes:
        chaos: weight of freshly generated chaos objects.
        cache: weight of chaos objects drawn from the cache.
        figures: weight of figures from ``figure_sets``.
        chaos_mode: "scatter", "attract" or "mix" (fresh objects and a built cache).
        attract_fraction: share of attract objects under "mix".
        angle_step: rotation grid of chaos objects (rad); 0 for continuous.
        workspace: chaos objects' piece centroids are drawn in [-workspace, workspace]^2 (m)
            before the attraction; the camera view (``env.view_extent``) bounds the rest.
        cache_path: an ``.npz`` cache to load; built and saved there if missing.
        cache_size: objects to generate when the cache has to be built.
        cache_seed: seed of a built cache.
        figure_sets: figure files or folders; "builtin" is the shipped library.
    """

    chaos: float = 0.0
    cache: float = 1.0
    figures: float = 0.0
    chaos_mode: str = "mix"
    attract_fraction: float = 0.5
    angle_step: float = 0.7853981633974483
    workspace: float = 0.10
    cache_path: str | None = None
    cache_size: int = 2048
    cache_seed: int = 12345
    figure_sets: list[str] = field(default_factory=lambda: ["builtin"])

    def chaos_config(self, view_extent: float = 0.26) -> ChaosConfig:
        """The chaos generator's settings for a camera view ``view_extent`` metres wide: every
        object lies inside the view, 5 mm from its edges."""
        return ChaosConfig(mode=self.chaos_mode, attract_fraction=self.attract_fraction, angle_step=self.angle_step,
                           workspace=self.workspace, view_half=view_extent / 2 - 0.005)


@dataclass
class TaskBatch:
    """Targets for n worlds: poses (n, P, 3), source index (n,), and figure index (n,) or -1."""

    poses: np.ndarray
    source: np.ndarray
    figure: np.ndarray


class TaskSampler:
    """Draws target assemblies for resets.

    Args:
        piece_set: the pieces.
        cfg: the mix and its sources.
        figures: figures to use instead of loading ``cfg.figure_sets`` (optional).
        view_extent: width of the camera view (m); chaos objects lie inside it.
    """

    def __init__(self, piece_set: PieceSet, cfg: TaskConfig = TaskConfig(), figures: list[Figure] | None = None,
                 view_extent: float = 0.26):
        self.piece_set = piece_set
        self.cfg = cfg
        self.view_extent = view_extent
        w = np.array([cfg.chaos, cfg.cache, cfg.figures], dtype=np.float64)
        if (w < 0).any() or w.sum() <= 0:
            raise ValueError(f"task mix weights must be >= 0 with a positive sum, got chaos/cache/figures = {w}")
        self.weights = w / w.sum()
        self.cache: ChaosCache | None = None
        if self.weights[1] > 0:
            self.cache = self._load_or_build_cache()
        self.figures: list[Figure] = []
        if self.weights[2] > 0:
            self.figures = figures if figures is not None else self._load_figures()
            self.figures = [f for f in self.figures if not f.has_mirrored]
            if not self.figures:
                raise ValueError("task: figure weight > 0 but no usable figures (mirrored ones are skipped)")
        self._figure_poses = np.stack([f.poses for f in self.figures]) if self.figures else None

    def _load_or_build_cache(self) -> ChaosCache:
        path = self.cfg.cache_path
        if path and Path(path).exists():
            cache = ChaosCache.load(path, self.piece_set)
            # A cache built for a wider view would hand the policy pieces it cannot see.
            reach = np.abs(self.piece_set.footprints(cache.poses)).max()
            half = self.view_extent / 2
            if reach > half:
                raise ValueError(f"{path}: chaos cache objects reach {reach:.3f} m from the centre, outside this "
                                 f"view's ±{half:.3f} m; delete it or set task.cache_path to rebuild")
            return cache
        log.info("building a chaos cache of %d objects", self.cfg.cache_size)
        cache = ChaosCache.build(self.piece_set, self.cfg.cache_size, self.cfg.cache_seed, self.cfg.chaos_config(self.view_extent))
        if path:
            cache.save(path)
        return cache

    def _load_figures(self) -> list[Figure]:
        from mrchaos.figure_io import load_figures
        from mrchaos.library import builtin_figures

        out: list[Figure] = []
        for src in self.cfg.figure_sets:
            if src == "builtin":
                out.extend(builtin_figures())
            else:
                fs = load_figures(src)
                for fid, why in fs.rejected:
                    log.warning("skipping figure %s: %s", fid, why)
                out.extend(f for f in fs.figures if f.piece_set.name == self.piece_set.name)
        return out

    def sample(self, n: int, rng: np.random.Generator) -> TaskBatch:
        """Targets for n worlds."""
        source = rng.choice(3, size=n, p=self.weights)
        poses = np.zeros((n, len(self.piece_set), 3))
        figure = np.full(n, -1, dtype=np.int64)
        idx = np.flatnonzero(source == 0)
        if len(idx):
            poses[idx] = generate(self.piece_set, len(idx), rng, self.cfg.chaos_config(self.view_extent))[0]
        idx = np.flatnonzero(source == 1)
        if len(idx):
            poses[idx] = self.cache.sample(len(idx), rng)
        idx = np.flatnonzero(source == 2)
        if len(idx):
            figure[idx] = rng.integers(0, len(self.figures), len(idx))
            poses[idx] = self._figure_poses[figure[idx]]
        return TaskBatch(poses, source, figure)
