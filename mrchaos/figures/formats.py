"""Reading and writing figure sets: the interchange JSON, and dispatch to other formats.

Interchange JSON (as in the MRChaos evaluation set)::

    {"name": ..., "units": "metre", "piece_order": [...],
     "figures": [{"id": ..., "family": ..., "name": ...,
                  "pieces": [{"piece": name, "vertices": [[x, y], ...]}, ...]}]}

Vertices are world-frame, counter-clockwise, in metres. Extra keys are ignored on
read. ``piece_set`` names a registered piece set (default ``tangram7``).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from mrchaos.core.atomic import write_atomic
from mrchaos.figures.figure import (
    FAMILIES,
    Figure,
    FigureError,
    FigureSet,
    figure_from_polygons,
)
from mrchaos.figures.kilogram import load_kilogram
from mrchaos.figures.pieces import PieceSet, get_piece_set

__all__ = ["load_figures", "load_json", "save_figures", "figure_to_dict"]

_UNITS = {"metre": 1.0, "meter": 1.0, "m": 1.0, "millimetre": 1e-3, "millimeter": 1e-3, "mm": 1e-3}


def _parse_figure(entry: object, index: int, piece_set: PieceSet, scale: float, source: str) -> Figure:
    if not isinstance(entry, dict):
        raise FigureError(f"{source}: figure #{index} is not an object")
    fig_id = str(entry.get("id", f"#{index}"))
    where = f"{source}: figure {fig_id!r}"
    pieces = entry.get("pieces")
    if not isinstance(pieces, list):
        raise FigureError(f"{where}: missing 'pieces' list")
    by_name: dict[str, list] = {}
    for k, pc in enumerate(pieces):
        if not isinstance(pc, dict) or "piece" not in pc or "vertices" not in pc:
            raise FigureError(f"{where}: piece entry #{k} needs 'piece' and 'vertices'")
        if pc["piece"] in by_name:
            raise FigureError(f"{where}: piece {pc['piece']!r} appears twice")
        by_name[pc["piece"]] = pc["vertices"]
    missing = [n for n in piece_set.names if n not in by_name]
    extra = [n for n in by_name if n not in piece_set.names]
    if missing or extra:
        raise FigureError(
            f"{where}: wrong piece count or names for {piece_set.name} (missing {missing}, unknown {extra})"
        )
    polys = []
    for n in piece_set.names:
        try:
            polys.append(np.asarray(by_name[n], dtype=np.float64) * scale)
        except (TypeError, ValueError):
            raise FigureError(f"{where}: piece {n}: vertices are not numbers") from None
    family = entry.get("family")
    if family is not None and family not in FAMILIES:
        raise FigureError(f"{where}: unknown family {family!r}; families: {list(FAMILIES)}")
    return figure_from_polygons(
        piece_set, polys, fig_id, name=str(entry.get("name", fig_id)), family=family, source=source
    )


def load_json(path: str | os.PathLike, validate: bool = True) -> FigureSet:
    """Load an interchange JSON figure set. Malformed files raise; invalid figures are rejected by id."""
    source = str(path)
    try:
        with open(path, encoding="utf-8") as f:
            data = json.load(f)
    except FileNotFoundError:
        raise FigureError(f"{source}: no such figure file") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise FigureError(f"{source}: not valid JSON ({e})") from None
    if not isinstance(data, dict) or not isinstance(data.get("figures"), list):
        raise FigureError(f"{source}: expected an object with a 'figures' list")
    units = data.get("units", "metre")
    if units not in _UNITS:
        raise FigureError(f"{source}: unknown units {units!r}; use one of {sorted(_UNITS)}")
    try:
        piece_set = get_piece_set(data.get("piece_set", "tangram7"))
    except KeyError as e:
        raise FigureError(f"{source}: {e.args[0]}") from None
    order = data.get("piece_order")
    if order is not None and list(order) != list(piece_set.names):
        raise FigureError(f"{source}: piece_order {order} differs from {piece_set.name} {list(piece_set.names)}")
    out = FigureSet(str(data.get("name", Path(source).stem)), [], source=source)
    seen: set[str] = set()
    for i, entry in enumerate(data["figures"]):
        try:
            fig = _parse_figure(entry, i, piece_set, _UNITS[units], source)
            if fig.id in seen:
                raise FigureError(f"{fig.where}: duplicate figure id")
            seen.add(fig.id)
            if validate:
                fig.validate()
            out.figures.append(fig)
        except FigureError as e:
            fid = entry.get("id", f"#{i}") if isinstance(entry, dict) else f"#{i}"
            out.rejected.append((str(fid), str(e)))
    return out


def load_figures(path: str | os.PathLike, validate: bool = True) -> FigureSet:
    """Load figures from an interchange JSON file, a KILOGRAM SVG file, or a folder of SVGs."""
    p = Path(path)
    if p.is_dir() or p.suffix.lower() == ".svg":
        return load_kilogram(p, validate=validate)
    if p.suffix.lower() == ".json":
        return load_json(p, validate=validate)
    if not p.exists():
        raise FigureError(f"{p}: no such figure file or folder")
    raise FigureError(f"{p}: unknown figure format (expected .json, .svg or a folder of .svg)")


def figure_to_dict(fig: Figure) -> dict:
    """Interchange-JSON entry of a figure (vertices rounded to a nanometre, so touching pieces stay touching)."""
    entry: dict = {"id": fig.id, "name": fig.name}
    if fig.family is not None:
        entry["family"] = fig.family
    entry["pieces"] = [
        {"piece": n, "vertices": np.round(fig.piece_polygon(i), 9).tolist()} for i, n in enumerate(fig.piece_set.names)
    ]
    if fig.has_mirrored:
        entry["mirrored"] = [fig.piece_set.names[i] for i in np.flatnonzero(fig.mirrored)]
    return entry


def save_figures(figures: list[Figure], path: str | os.PathLike, name: str, description: str = "") -> None:
    """Write figures as interchange JSON (atomically)."""
    if not figures:
        raise ValueError("no figures to write")
    ps = figures[0].piece_set
    data = {
        "name": name,
        "description": description,
        "units": "metre",
        "piece_set": ps.name,
        "piece_order": list(ps.names),
        "figures": [figure_to_dict(f) for f in figures],
    }
    write_atomic(path, json.dumps(data, indent=1) + "\n")
