"""PNG contact sheets: figures drawn in colour, and silhouette-versus-assembly pairs.

Drawing is vector (PIL polygons at a chosen resolution), not the 120x120
observation raster, so that a person can judge whether a figure reads as its
subject.
"""

from __future__ import annotations

import io
import math
import os
from collections.abc import Sequence

import numpy as np
from PIL import Image, ImageDraw

from mrchaos.core.raster import View

__all__ = ["PIECE_COLOURS", "draw_polygons", "tile_sheet", "figure_sheet", "pair_sheet", "save_png"]

#: One colour per piece id (cycled for larger sets).
PIECE_COLOURS = [
    (228, 26, 28),
    (55, 126, 184),
    (77, 175, 74),
    (152, 78, 163),
    (255, 127, 0),
    (166, 86, 40),
    (247, 129, 191),
    (153, 153, 153),
]


def draw_polygons(
    polygons: Sequence[np.ndarray],
    tile: int = 240,
    view: View = View(),
    colours: Sequence[tuple[int, int, int]] | None = None,
    background: tuple[int, int, int] = (255, 255, 255),
    outline: tuple[int, int, int] | None = (40, 40, 40),
) -> Image.Image:
    """Draw world-frame polygons (metres) into a tile covering the camera view."""
    img = Image.new("RGB", (tile, tile), background)
    d = ImageDraw.Draw(img)
    scale = tile / view.extent
    for i, poly in enumerate(polygons):
        pts = [((x + view.extent / 2) * scale, (view.extent / 2 - y) * scale) for x, y in np.asarray(poly)]
        colour = (colours or PIECE_COLOURS)[i % len(colours or PIECE_COLOURS)]
        d.polygon(pts, fill=colour, outline=outline)
    return img


def tile_sheet(tiles: list[Image.Image], labels: list[str], columns: int, label_h: int = 16) -> Image.Image:
    """Tiles in a grid of ``columns``, each under its label."""
    if not tiles:
        raise ValueError("nothing to draw")
    tw, th = tiles[0].size
    rows = math.ceil(len(tiles) / columns)
    sheet = Image.new("RGB", (columns * tw, rows * (th + label_h)), (255, 255, 255))
    d = ImageDraw.Draw(sheet)
    for k, (t, lab) in enumerate(zip(tiles, labels, strict=True)):
        x, y = (k % columns) * tw, (k // columns) * (th + label_h)
        sheet.paste(t, (x, y + label_h))
        d.text((x + 4, y + 2), lab[: max(8, tw // 7)], fill=(0, 0, 0))
        d.rectangle([x, y + label_h, x + tw - 1, y + label_h + th - 1], outline=(200, 200, 200))
    return sheet


def figure_sheet(figures: Sequence, columns: int = 8, tile: int = 200, view: View = View()) -> Image.Image:
    """A contact sheet of figures, one coloured tile each, labelled with name and family."""
    tiles, labels = [], []
    for f in figures:
        polys = [f.piece_polygon(i) for i in range(len(f.piece_set))]
        tiles.append(draw_polygons(polys, tile, view))
        fam = getattr(f, "family", None) or ""
        labels.append(f"{f.name} {fam}".strip())
    return tile_sheet(tiles, labels, columns)


def pair_sheet(pairs: Sequence[tuple[np.ndarray, np.ndarray, str]], columns: int = 6, scale: int = 2) -> Image.Image:
    """Silhouette-versus-result pairs: each entry is (silhouette HxW bool, view HxW, label).

    The result image is drawn in grey over the silhouette in light blue, so spill
    and holes are visible at a glance.
    """
    tiles, labels = [], []
    for sil, cur, lab in pairs:
        sil = np.asarray(sil, dtype=bool)
        occ = np.asarray(cur) > 0
        rgb = np.full(sil.shape + (3,), 255, dtype=np.uint8)
        rgb[sil] = (170, 200, 240)
        rgb[occ & sil] = (60, 60, 60)
        rgb[occ & ~sil] = (220, 60, 60)
        img = Image.fromarray(rgb).resize((sil.shape[1] * scale, sil.shape[0] * scale), Image.Resampling.NEAREST)
        tiles.append(img)
        labels.append(lab)
    return tile_sheet(tiles, labels, columns)


def save_png(img: Image.Image, path: str | os.PathLike) -> None:
    """Save a PNG atomically."""
    from mrchaos.core.atomic import write_atomic

    buf = io.BytesIO()
    img.save(buf, format="PNG")
    write_atomic(path, buf.getvalue())
