"""The built-in library of human-designed tangram figures, authored for this project.

It is the default evaluation set, so the package runs without any external data.
The figures live in ``mrchaos/data/library.json`` (interchange format); the script
that authors them is ``tools/author_library.py``.
"""

from __future__ import annotations

import copy
from functools import lru_cache
from importlib import resources

from mrchaos.figures.figure import Figure, FigureError, FigureSet
from mrchaos.figures.formats import load_json

__all__ = ["builtin_figures", "library_path"]


def library_path() -> str:
    """Filesystem path of the shipped library JSON."""
    return str(resources.files("mrchaos") / "data" / "library.json")


@lru_cache(maxsize=1)
def _load() -> FigureSet:
    fs = load_json(library_path())
    if fs.rejected:
        raise FigureError(f"built-in library has invalid figures: {fs.rejected}")
    return fs


def builtin_figures() -> list[Figure]:
    """The built-in figures (validated), in file order; fresh copies, so callers may edit them."""
    return [copy.deepcopy(f) for f in _load().figures]
