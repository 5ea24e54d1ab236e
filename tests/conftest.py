"""Shared fixtures. Data in ../shared is optional: tests that need it skip with a reason when it is absent."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

SHARED = Path(__file__).resolve().parents[2] / "shared"
MRCHAOS104 = SHARED / "figures" / "mrchaos104.json"
KILOGRAM = SHARED / "figures" / "kilogram_samples"


@pytest.fixture(scope="session")
def mrchaos104():
    if not MRCHAOS104.exists():
        pytest.skip(f"{MRCHAOS104} not present (evaluation data lives outside the repo)")
    from mrchaos.figures.formats import load_figures

    return load_figures(MRCHAOS104)


@pytest.fixture(scope="session")
def kilogram_dir() -> Path:
    if not KILOGRAM.exists():
        pytest.skip(f"{KILOGRAM} not present")
    return KILOGRAM


@pytest.fixture(scope="session")
def tangram():
    from mrchaos.figures.pieces import tangram7

    return tangram7()


@pytest.fixture(scope="session")
def rendering() -> str:
    """The OpenGL backend MuJoCo renders with. In CI (``CI=true``) a missing one fails the
    test; elsewhere the test skips, naming what to install."""
    from mrchaos.sim.opengl import RenderingUnavailable, choose_backend, make_renderer

    try:
        backend = choose_backend()
        import mujoco

        model = mujoco.MjModel.from_xml_string("<mujoco><worldbody><geom size='0.1'/></worldbody></mujoco>")
        make_renderer(model, 8, 8).close()
    except RenderingUnavailable as e:
        if os.environ.get("CI", "").lower() in ("1", "true", "yes"):
            pytest.fail(f"rendering must work in CI: {e}")
        pytest.skip(str(e))
    return backend


def require_extra(package: str, extra: str):
    """Import an optional extra's package. In CI (``CI=true``, which installs the test extra and
    with it ``[ray,tensorboard]``) a missing one fails the test; elsewhere it skips, naming the install."""
    import importlib

    try:
        return importlib.import_module(package)
    except ImportError:
        msg = f"{package} is not installed: pip install -c constraints.txt -e '.[{extra}]'"
        if os.environ.get("CI", "").lower() in ("1", "true", "yes"):
            pytest.fail(f"the test extra must bring it in CI: {msg}")
        pytest.skip(msg)
