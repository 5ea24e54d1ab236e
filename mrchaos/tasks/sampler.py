"""The task's config and its target sampler: where each episode's target comes from.

Targets are chaos objects (drawn fresh, or from a pre-generated cache) or
figures from figure sets, in a mix set by config. Everything is drawn from the
caller's generator, so a seeded environment gets the same targets every run.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mrchaos.core.raster import View
from mrchaos.figures.figure import Figure
from mrchaos.figures.formats import load_figures
from mrchaos.figures.library import builtin_figures
from mrchaos.figures.pieces import PieceSet
from mrchaos.tasks.chaos import MODES, ChaosCache, ChaosConfig, generate

__all__ = ["TaskConfig", "MixConfig", "CacheConfig", "TargetBatch", "TargetSampler", "SOURCES"]

log = logging.getLogger(__name__)

#: Target sources, by index.
SOURCES = ("chaos", "cache", "figures")


@dataclass
class MixConfig:
    """Weights of the target sources (normalised): fresh chaos objects, the chaos cache, figures."""

    chaos: float = 0.0
    cache: float = 1.0
    figures: float = 0.0


@dataclass
class CacheConfig:
    """A pre-generated chaos cache: an ``.npz`` at ``path`` (built and saved there if missing;
    relative paths are resolved against the working directory), ``size`` objects, ``seed``."""

    path: str | None = None
    size: int = 2048
    seed: int = 12345


@dataclass
class TaskConfig:
    """The task: which preset (piece set, view, grid, goals) and where its training targets come from.

    Attributes:
        preset: a task of :data:`mrchaos.presets.PRESETS` (tangram, cutlery, soda); it sets the
            env's piece set, view, grid and slot rule, and the chaos workspace, unless the
            config sets them itself.
        mix: the weights of the target sources.
        chaos: how chaos objects are drawn (the camera view bounds them).
        cache: the chaos cache.
        figure_sets: figure files or folders for the ``figures`` source; "builtin" is the shipped library.
    """

    preset: str = "tangram"
    mix: MixConfig = field(default_factory=MixConfig)
    chaos: ChaosConfig = field(default_factory=ChaosConfig)
    cache: CacheConfig = field(default_factory=CacheConfig)
    figure_sets: list[str] = field(default_factory=lambda: ["builtin"])

    def given_targets(self) -> TaskConfig:
        """This task for an env whose targets are all given at reset (evaluation, demonstrations):
        fresh chaos only, so that no cache is loaded or built for a sampler that is never asked."""
        return dataclasses.replace(self, mix=MixConfig(chaos=1.0, cache=0.0, figures=0.0))

    def check_flip(self, flip: bool) -> None:
        """Refuse chaos objects with turned-over pieces (``chaos.mirror_prob > 0``) when the env
        cannot turn pieces over and a chaos source (fresh or cached) is drawn from: training on
        such targets would pay for faces the policy can never show. Figures are filtered instead."""
        if self.chaos.mirror_prob > 0 and not flip and self.mix.chaos + self.mix.cache > 0:
            raise ValueError(
                f"task.chaos.mirror_prob = {self.chaos.mirror_prob} draws chaos objects with "
                "turned-over pieces, which need env.grid.flip: true; or set task.chaos.mirror_prob=0"
            )


@dataclass
class TargetBatch:
    """Targets for n worlds: poses (n, P, 3), source index (n,), figure index (n,) or -1, and
    (n, P) bool mirrored, the pieces that lie turned over (default: none)."""

    poses: np.ndarray
    source: np.ndarray
    figure: np.ndarray
    mirrored: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.mirrored is None:
            self.mirrored = np.zeros(self.poses.shape[:2], dtype=bool)


class TargetSampler:
    """Draws target assemblies for resets.

    Args:
        piece_set: the pieces.
        cfg: the task: its mix and sources.
        figures: figures to use instead of loading ``cfg.figure_sets`` (optional).
        view: the camera view; chaos objects lie inside it.
        flip: the env can turn pieces over, so figures that need a mirrored piece are used, not skipped.
    """

    def __init__(
        self,
        piece_set: PieceSet,
        cfg: TaskConfig | None = None,
        figures: list[Figure] | None = None,
        view: View = View(),
        flip: bool = False,
    ):
        self.piece_set = piece_set
        cfg = cfg if cfg is not None else TaskConfig()  # a fresh default: the sampler keeps and reads it
        self.cfg = cfg
        self.view = view
        mix = cfg.mix
        w = np.array([mix.chaos, mix.cache, mix.figures], dtype=np.float64)
        if (w < 0).any() or w.sum() <= 0:
            raise ValueError(f"task mix weights must be >= 0 with a positive sum, got chaos/cache/figures = {w}")
        self.weights = w / w.sum()
        cfg.check_flip(flip)  # before any cache is built
        self.cache: ChaosCache | None = None
        if self.weights[1] > 0:
            self.cache = self._load_or_build_cache()
        self.figures: list[Figure] = []
        if self.weights[2] > 0:
            self.figures = figures if figures is not None else self._load_figures()
            if not flip:
                self.figures = [f for f in self.figures if not f.has_mirrored]
            if not self.figures:
                raise ValueError(
                    "task: figure weight > 0 but no usable figures (mirrored ones are skipped without env.grid.flip)"
                )
        self._figure_poses = np.stack([f.poses for f in self.figures]) if self.figures else None
        self._figure_mirrored = np.stack([f.mirrored for f in self.figures]) if self.figures else None

    def _load_or_build_cache(self) -> ChaosCache:
        path = self.cfg.cache.path
        if path and Path(path).exists():
            cache = ChaosCache.load(path, self.piece_set)
            # A cache built for a wider view would hand the policy pieces it cannot see.
            reach = np.abs(self.piece_set.footprints(cache.poses, cache.mirrored)).max()
            half = self.view.extent / 2
            if reach > half:
                raise ValueError(
                    f"{path}: chaos cache objects reach {reach:.3f} m from the centre, outside this "
                    f"view's ±{half:.3f} m; delete it or set task.cache_path to rebuild"
                )
            # A cache drawn with another mirroring rule would train on the wrong faces.
            if cache.mirrored.any() != (self.cfg.chaos.mirror_prob > 0):
                had = "has" if cache.mirrored.any() else "has no"
                raise ValueError(
                    f"{path}: chaos cache {had} mirrored pieces but task.chaos.mirror_prob is "
                    f"{self.cfg.chaos.mirror_prob}; delete it or set task.cache.path to rebuild"
                )
            # A cache drawn by other generators would train on other objects than the config says.
            shares = self.cfg.chaos.shares()
            present = set(np.unique(cache.modes).tolist())
            drawn = {m for m, w in enumerate(shares) if w > 0}
            if not present <= drawn or (shares[2] > 0 and 2 not in present):
                have = ", ".join(MODES[m] for m in sorted(present))
                raise ValueError(
                    f"{path}: chaos cache holds {have} objects but task.chaos draws "
                    f"{', '.join(MODES[m] for m in sorted(drawn))}; delete it or set task.cache.path to rebuild"
                )
            return cache
        log.info("building a chaos cache of %d objects", self.cfg.cache.size)
        cache = ChaosCache.build(self.piece_set, self.cfg.cache.size, self.cfg.cache.seed, self.cfg.chaos, self.view)
        if path:
            cache.save(path)
        return cache

    def _load_figures(self) -> list[Figure]:
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

    def sample(self, n: int, rng: np.random.Generator) -> TargetBatch:
        """Targets for n worlds."""
        source = rng.choice(3, size=n, p=self.weights)
        poses = np.zeros((n, len(self.piece_set), 3))
        mirrored = np.zeros((n, len(self.piece_set)), dtype=bool)
        figure = np.full(n, -1, dtype=np.int64)
        idx = np.flatnonzero(source == 0)
        if len(idx):
            poses[idx], _, mirrored[idx] = generate(self.piece_set, len(idx), rng, self.cfg.chaos, self.view)
        idx = np.flatnonzero(source == 1)
        if len(idx):
            assert self.cache is not None  # built whenever the mix draws from it
            poses[idx], mirrored[idx] = self.cache.sample(len(idx), rng)
        idx = np.flatnonzero(source == 2)
        if len(idx):
            assert self._figure_poses is not None and self._figure_mirrored is not None  # the mix has figures
            figure[idx] = rng.integers(0, len(self.figures), len(idx))
            poses[idx] = self._figure_poses[figure[idx]]
            mirrored[idx] = self._figure_mirrored[figure[idx]]
        return TargetBatch(poses, source, figure, mirrored)
