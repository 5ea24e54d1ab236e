"""The extension tasks beyond tangram, and the goal configurations we authored for them.

A :class:`TaskPreset` says what a task needs beyond its piece set: the camera view, the
action grid and the slot rule (the same settings ``conf/<task>.yaml`` trains with). Goals
are :class:`mrchaos.figure.Figure` objects written here by hand: table settings for
cutlery, group shapes for soda cans. They are never used in training (the configs train
on chaos objects only); the bench evaluates on them.

Poses are centroid poses (m, rad). Cutlery lies along +x at angle 0, handle first, so
angle pi/2 points the head up (+y).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from mrchaos.chaos import ChaosConfig
from mrchaos.figure import Figure, FigureError
from mrchaos.pieces import get_piece_set
from mrchaos.raster import View
from mrchaos.task import TaskConfig

__all__ = ["TaskPreset", "TASKS", "cutlery_goals", "soda_goals", "task_goals"]

UP, DOWN, LEFT, RIGHT = math.pi / 2, -math.pi / 2, math.pi, 0.0


def cutlery_goals() -> list[Figure]:
    """Ten cutlery goals (knife, spoon, fork poses)."""
    ps = get_piece_set("cutlery")
    d = math.pi / 4
    goals = {
        # A place setting around a plate area: fork left, knife right (edge in), spoon above.
        "setting": [(0.13, 0.0, UP), (0.0, 0.155, LEFT), (-0.13, 0.0, UP)],
        # Soup setting: the spoon right of the knife.
        "setting_soup": [(0.09, 0.0, UP), (0.15, 0.0, UP), (-0.12, 0.0, UP)],
        # Dessert setting: fork and spoon above the plate, knife at the right.
        "setting_dessert": [(0.14, -0.02, UP), (0.0, 0.17, LEFT), (0.0, 0.12, RIGHT)],
        # Finished meal: knife and fork side by side, handles to the lower right.
        "finished": [(0.01, 0.025, 3 * d), (-0.05, -0.15, RIGHT), (-0.025, -0.01, 3 * d)],
        # A chevron: knife and fork leaning in, heads apart; spoon flat below.
        "chevron": [(0.085, 0.02, 3 * d), (0.0, -0.14, RIGHT), (-0.085, 0.02, d)],
        # A fan: three pieces spread from handles at the bottom.
        "fan": [(0.09, 0.03, d), (0.0, 0.06, UP), (-0.09, 0.03, 3 * d)],
        # All three upright, side by side.
        "parallel": [(-0.05, 0.0, UP), (0.0, 0.0, UP), (0.05, 0.0, UP)],
        # All three lying horizontally, stacked in rows, alternating directions.
        "rows": [(0.0, 0.06, RIGHT), (0.0, 0.0, LEFT), (0.0, -0.06, RIGHT)],
        # An open triangle.
        "triangle": [(0.0, -0.085, RIGHT), (0.074, 0.043, 2 * math.pi / 3), (-0.074, 0.043, -2 * math.pi / 3)],
        # Diagonal parallels.
        "diagonal": [(-0.045, 0.045, d), (0.0, 0.0, d), (0.045, -0.045, d)],
    }
    return [Figure(f"cutlery-{k}", ps, np.array(v), name=k.replace("_", " "), source="mrchaos.goals")
            for k, v in goals.items()]


def _cans(points: list[tuple[float, float]]) -> np.ndarray:
    return np.array([(x, y, 0.0) for x, y in points])


def soda_goals(pitch: float = 0.070) -> list[Figure]:
    """Ten soda goals of 3 to 6 cans: rows, triangles, squares, rings. ``pitch`` is the
    distance between neighbouring cans (m; a can is 66 mm across)."""
    p = pitch
    h = p * math.sqrt(3) / 2

    def ring(n: int, r: float) -> list[tuple[float, float]]:
        return [(r * math.cos(2 * math.pi * k / n + math.pi / 2), r * math.sin(2 * math.pi * k / n + math.pi / 2))
                for k in range(n)]

    goals = {
        "row3": [(-p, 0.0), (0.0, 0.0), (p, 0.0)],
        "row4": [(-1.5 * p, 0.0), (-0.5 * p, 0.0), (0.5 * p, 0.0), (1.5 * p, 0.0)],
        "column5": [(0.0, k * p) for k in (-2, -1, 0, 1, 2)],
        "block6": [(x, y) for y in (-p / 2, p / 2) for x in (-p, 0.0, p)],
        "triangle3": [(-p / 2, -h / 3), (p / 2, -h / 3), (0.0, 2 * h / 3)],
        "triangle6": [(-p, -h), (0.0, -h), (p, -h), (-p / 2, 0.0), (p / 2, 0.0), (0.0, h)],
        "square4": [(-p / 2, -p / 2), (p / 2, -p / 2), (-p / 2, p / 2), (p / 2, p / 2)],
        "ring5": ring(5, 0.07),
        "ring6": ring(6, 0.08),
        "diagonal4": [(k * p / math.sqrt(2), k * p / math.sqrt(2)) for k in (-1.5, -0.5, 0.5, 1.5)],
    }
    return [Figure(f"soda-{k}", get_piece_set(f"soda{len(v)}"), _cans(v), name=k, source="mrchaos.goals")
            for k, v in goals.items()]


@dataclass(frozen=True)
class TaskPreset:
    """An extension task: its piece sets, view, grid and slot rule, and its authored goals.

    Attributes:
        piece_set: the set it trains on.
        view_extent, grid_half_range, grid_ntheta, twin_slots: env settings (as in its config).
        goals: the authored goal configurations.
        random_sets: piece sets of its Random family (soda draws every can count).
    """

    piece_set: str
    view_extent: float
    grid_half_range: float
    grid_ntheta: int
    twin_slots: str
    workspace: float
    goals: Callable[[], list[Figure]]
    random_sets: tuple[str, ...]

    def chaos_config(self) -> ChaosConfig:
        """The chaos generator's settings of the task: its workspace, inside its view."""
        return TaskConfig(workspace=self.workspace).chaos_config(self.view_extent)

    def env_overrides(self) -> dict:
        """EnvConfig fields of the task."""
        return {"piece_set": self.piece_set, "view_extent": self.view_extent, "grid_half_range": self.grid_half_range,
                "grid_ntheta": self.grid_ntheta, "twin_slots": self.twin_slots}


TASKS: dict[str, TaskPreset] = {
    "cutlery": TaskPreset("cutlery", 0.40, 0.16, 8, "shared", 0.14, cutlery_goals, ("cutlery",)),
    "soda": TaskPreset("soda6", 0.44, 0.18, 1, "exclusive", 0.15, soda_goals,
                       ("soda3", "soda4", "soda5", "soda6")),
}


def task_goals(name: str) -> list[Figure]:
    """The validated goals of task ``name`` (inside its view, no overlaps)."""
    preset = TASKS[name]
    goals = preset.goals()
    for g in goals:
        try:
            g.validate(View(extent=preset.view_extent))
        except FigureError as e:
            raise FigureError(f"authored goal: {e}") from None
    return goals
