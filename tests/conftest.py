"""Shared fixtures. Data in ../shared is optional: tests that need it skip with a reason when it is absent."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

# MuJoCo fixes its OpenGL backend when first imported, and test modules import torchrl
# (which imports mujoco) before mrchaos: choose headless rendering before any of them.
if "MUJOCO_GL" not in os.environ and not os.environ.get("DISPLAY"):
    os.environ["MUJOCO_GL"] = "osmesa"

SHARED = Path(__file__).resolve().parents[2] / "shared"
MRCHAOS104 = SHARED / "figures" / "mrchaos104.json"
KILOGRAM = SHARED / "figures" / "kilogram_samples"


@pytest.fixture(scope="session")
def mrchaos104():
    if not MRCHAOS104.exists():
        pytest.skip(f"{MRCHAOS104} not present (evaluation data lives outside the repo)")
    from mrchaos.figure_io import load_figures

    return load_figures(MRCHAOS104)


@pytest.fixture(scope="session")
def kilogram_dir() -> Path:
    if not KILOGRAM.exists():
        pytest.skip(f"{KILOGRAM} not present")
    return KILOGRAM


@pytest.fixture(scope="session")
def tangram():
    from mrchaos.pieces import tangram7

    return tangram7()
