"""The task presets (tangram, cutlery, soda) and the goal configurations we authored for them.

A :class:`TaskPreset` says what a task needs beyond its piece set: the camera view, the
action grid, the slot rule and the chaos workspace (``conf/<task>.yaml`` names the preset
and inherits them), and what it is evaluated on. Tangram's goals are the built-in library. Goals
are :class:`mrchaos.figures.figure.Figure` objects written here by hand: table settings for
cutlery, group shapes for soda cans. They are never used in training (the configs train
on chaos objects only); the bench evaluates on them.

Poses are centroid poses (m, rad). Cutlery lies along +x at angle 0, handle first, so
angle pi/2 points the head up (+y).
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from mrchaos.core.raster import View
from mrchaos.figures.figure import FAMILIES, Figure, FigureError
from mrchaos.figures.library import builtin_figures
from mrchaos.figures.pieces import get_piece_set

__all__ = ["TaskPreset", "PRESETS", "get_preset", "cutlery_goals", "soda_goals"]

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
    return [
        Figure(f"cutlery-{k}", ps, np.array(v), name=k.replace("_", " "), source="mrchaos.tasks.presets")
        for k, v in goals.items()
    ]


def _cans(points: list[tuple[float, float]]) -> np.ndarray:
    return np.array([(x, y, 0.0) for x, y in points])


def soda_goals(pitch: float = 0.070) -> list[Figure]:
    """Ten soda goals of 3 to 6 cans: rows, triangles, squares, rings. ``pitch`` is the
    distance between neighbouring cans (m; a can is 66 mm across)."""
    p = pitch
    h = p * math.sqrt(3) / 2

    def ring(n: int, r: float) -> list[tuple[float, float]]:
        return [
            (r * math.cos(2 * math.pi * k / n + math.pi / 2), r * math.sin(2 * math.pi * k / n + math.pi / 2))
            for k in range(n)
        ]

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
    return [
        Figure(f"soda-{k}", get_piece_set(f"soda{len(v)}"), _cans(v), name=k, source="mrchaos.tasks.presets")
        for k, v in goals.items()
    ]


@dataclass(frozen=True)
class TaskPreset:
    """A task: its piece set, the env and chaos settings it needs, and what it is evaluated on.

    The settings are overrides of the configs' own defaults (tangram needs none): a config
    that names the preset (``task.preset``) gets them unless it sets a value itself.

    Attributes:
        name: the task's name (``mrchaos-bench --task``, ``task.preset``).
        piece_set: the set it trains on.
        env: nested overrides of the env config (``{"view": {"extent": 0.40}}``).
        chaos: overrides of the chaos generator's config (its workspace).
        goals: the evaluation figures: the built-in library, or goals authored here.
        random_sets: piece sets of its Random family (soda draws every can count).
        families: its bench families, Random first or last as Table I lists them.
        authored: True when its goals form one "Authored" family; False when they are split
            into H-Normal / H-Hard / H-Fiendish by the perimeter rule (the tangram's).
    """

    name: str
    piece_set: str
    env: dict = field(default_factory=dict)
    chaos: dict = field(default_factory=dict)
    goals: Callable[[], list[Figure]] = builtin_figures
    random_sets: tuple[str, ...] = ()
    families: tuple[str, ...] = ("Authored", "Random")
    authored: bool = True

    def config_overrides(self) -> dict:
        """The preset as a nested config fragment, for the loader to lay under a config's own keys."""
        return {"env": {"piece_set": self.piece_set, **copy.deepcopy(self.env)}, "task": {"chaos": dict(self.chaos)}}

    def goal_figures(self, view: View) -> list[Figure]:
        """The validated goals (inside ``view``, no overlaps)."""
        goals = self.goals()
        for g in goals:
            try:
                g.validate(view)
            except FigureError as e:
                raise FigureError(f"{self.name} goal: {e}") from None
        return goals


PRESETS: dict[str, TaskPreset] = {
    "tangram": TaskPreset("tangram", "tangram7", random_sets=("tangram7",), families=FAMILIES, authored=False),
    "cutlery": TaskPreset(
        "cutlery",
        "cutlery",
        env={"view": {"extent": 0.40}, "grid": {"half_range": 0.16}},
        chaos={"workspace": 0.14},
        goals=cutlery_goals,
        random_sets=("cutlery",),
    ),
    "soda": TaskPreset(
        "soda",
        "soda6",
        env={
            "view": {"extent": 0.44},
            "grid": {"half_range": 0.18, "ntheta": 1},
            "reward": {"twin_slots": "exclusive"},
        },
        chaos={"workspace": 0.15},
        goals=soda_goals,
        random_sets=("soda3", "soda4", "soda5", "soda6"),
    ),
}


def get_preset(name: str) -> TaskPreset:
    """The preset called ``name``; a KeyError lists the known ones."""
    if name not in PRESETS:
        raise KeyError(f"unknown task {name!r}; tasks: {sorted(PRESETS)}")
    return PRESETS[name]
