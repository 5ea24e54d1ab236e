"""Top-down orthographic rasteriser for batches of convex polygons.

This is where metres become pixels. The camera looks straight down at the table
centre; image row 0 is the +y edge, column 0 the -x edge, and a pixel belongs to
a polygon when its centre does; a centre exactly on an edge follows OpenGL's
top-left rule (in on the left and top edges, out on the right and bottom), so the
rasteriser and MuJoCo's renderer agree on shared and aligned edges. Polygons are turned into per-row spans (one
interval per convex polygon and image row), composited through a bit-set
difference array so the highest piece wins, which costs O(B*P*H) arithmetic plus
one cumulative sum over the image instead of a per-pixel inside test.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

__all__ = ["View", "Raster", "rasterize"]


@dataclass(frozen=True)
class View:
    """The camera's footprint: ``extent`` x ``extent`` metres imaged at ``size`` x ``size`` pixels.

    The default spans 0.26 m, which matches the reference perspective camera
    (0.25 m above the table, 55.37 deg vertical field of view, centre 120x120 crop)
    between the pieces' top faces (0.252 m) and the table (0.262 m).
    """

    extent: float = 0.26
    size: int = 120

    @property
    def pixel(self) -> float:
        """Pixel pitch in metres."""
        return self.extent / self.size

    def contains(self, xy: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """True where points (..., 2) lie inside the view shrunk by ``margin`` metres."""
        half = self.extent / 2 - margin
        return np.all(np.abs(np.asarray(xy)) <= half, axis=-1)

    def pixel_centres(self) -> tuple[np.ndarray, np.ndarray]:
        """World x of each column and world y of each row (metres)."""
        c = (np.arange(self.size) + 0.5) * self.pixel - self.extent / 2
        return c, -c


@dataclass
class Raster:
    """Rasterised scenes.

    Attributes:
        ids: (B, H, W) int8, the id of the visible piece at each pixel, -1 where empty.
        height: (B, H, W) float32, the visible top-surface height (m), 0 where empty;
            None unless requested.
    """

    ids: torch.Tensor
    height: torch.Tensor | None

    @property
    def occupied(self) -> torch.Tensor:
        """(B, H, W) bool, any piece visible."""
        return self.ids >= 0


def rasterize(
    polygons: np.ndarray | torch.Tensor,
    view: View = View(),
    visible: np.ndarray | torch.Tensor | None = None,
    heights: np.ndarray | torch.Tensor | None = None,
    need_height: bool = False,
    parts: np.ndarray | None = None,
) -> Raster:
    """Rasterise convex polygons into piece-id and height images.

    Args:
        polygons: (B, P, V, 2) world vertices in metres, counter-clockwise; a polygon
            with fewer vertices repeats its last one.
        view: camera footprint and resolution.
        visible: (B, P) bool, pieces to draw (default all).
        heights: (B, P) top-surface height of each piece (m). Where pieces overlap in
            the image the higher one is seen; ties go to the larger piece id (placed
            later). Default: all equal.
        need_height: also return the visible height image (costs one more gather).
        parts: (P',) the piece of every polygon when pieces are unions of convex parts
            (:meth:`mrchaos.figures.pieces.PieceSet.padded_parts`); ``visible`` and ``heights``
            are then per piece, and ``ids`` hold piece ids.
    """
    if parts is not None:
        idx = torch.as_tensor(np.asarray(parts), dtype=torch.long)
        if visible is not None:
            visible = torch.as_tensor(visible, dtype=torch.bool)[:, idx]
        if heights is not None:
            heights = torch.as_tensor(heights, dtype=torch.float32)[:, idx]
        out = rasterize(polygons, view, visible, heights, need_height)
        lut = torch.cat([idx, torch.full((1,), -1)]).to(torch.int8)
        return Raster(lut[out.ids.long()], out.height)
    poly = torch.as_tensor(polygons, dtype=torch.float32)
    b, p, v, _ = poly.shape
    h = w = view.size
    if visible is None:
        visible_t = torch.ones(b, p, dtype=torch.bool)
    else:
        visible_t = torch.as_tensor(visible, dtype=torch.bool)
    if heights is None:
        heights_t = torch.zeros(b, p)
    else:
        heights_t = torch.as_tensor(heights, dtype=torch.float32)
    if b == 0 or p == 0:
        return Raster(torch.full((b, h, w), -1, dtype=torch.int8), torch.zeros(b, h, w) if need_height else None)

    pix = view.pixel
    half = view.extent / 2
    # Vertex coordinates in pixel units: column grows with x, row with -y.
    cx = (poly[..., 0] + half) / pix
    ry = (half - poly[..., 1]) / pix
    # Scanline spans: for each image row, where its centre line crosses the polygon's
    # edges. Half-open crossing rule [min, max) counts a shared vertex once.
    yc = torch.arange(h, dtype=torch.float32) + 0.5
    ax, ay = cx[..., None], ry[..., None]  # (B, P, V, 1)
    bx, by = torch.roll(cx, -1, dims=-1)[..., None], torch.roll(ry, -1, dims=-1)[..., None]
    # Ties (a centre on an edge, up to 2e-3 px, about 4 micrometres) follow a fixed rule:
    # in on the top and left edges, out on the bottom and right ones. Ties are common
    # because the action grid and the pixel pitch are commensurate, and two pieces
    # that share an edge up to rounding (figure files keep micrometres) must not
    # leave a crack between them.
    eps = 2e-3
    crosses = (torch.minimum(ay, by) - eps <= yc) & (yc < torch.maximum(ay, by) - eps)
    dy = torch.where(by == ay, torch.ones(()), by - ay)
    xi = ax + (yc - ay) * (bx - ax) / dy  # (B, P, V, H)
    inf = torch.tensor(float("inf"))
    xl = torch.where(crosses, xi, inf).min(dim=2).values  # (B, P, H)
    xr = torch.where(crosses, xi, -inf).max(dim=2).values
    # Pixel c is covered when its centre c + 0.5 lies in [xl, xr).
    cl = torch.ceil(xl - 0.5 - eps).clamp(0, w)
    cr = torch.ceil(xr - 0.5 - eps).clamp(0, w)
    has = (cr > cl) & visible_t[..., None]
    cl = torch.where(has, cl, torch.zeros(())).long()
    cr = torch.where(has, cr, torch.zeros(())).long()

    # Each piece sets bit ``id`` along its spans through a difference array, so a
    # cumulative sum gives, per pixel, the set of pieces there. Sums wrap modulo
    # 2**bits, which is exact because every true value fits. The visible piece is the
    # highest set bit when priority follows the id (later pieces on top); pixels
    # where several pieces meet are then re-decided by height, which touches few pixels.
    dtype = _mask_dtype(p)
    bit = torch.where(has, (1 << torch.arange(p))[None, :, None], torch.zeros((), dtype=torch.long)).to(dtype)
    base = (torch.arange(b)[:, None, None] * h + torch.arange(h)[None, None, :]) * (w + 1)
    diff = torch.zeros(b * h * (w + 1), dtype=dtype)
    diff.index_add_(0, (base + cl).reshape(-1), bit.reshape(-1))
    diff.index_add_(0, (base + cr).reshape(-1), -bit.reshape(-1))
    mask = torch.cumsum(diff.view(b, h, w + 1), dim=2, dtype=dtype)[..., :w]
    ids = _highest_bit(mask).to(torch.int8)
    if heights is not None:
        order = torch.argsort(heights_t * 1e4 + torch.arange(p).float() * 1e-3, dim=1, stable=True)
        identity = torch.arange(p).expand(b, p)
        scenes = (order != identity).any(1)
        if bool(scenes.any()):
            rank = torch.empty_like(order)
            rank.scatter_(1, order, identity.contiguous())
            sub = mask[scenes]
            multi = (sub & (sub - 1)) != 0
            sb, sr, sc = torch.nonzero(multi, as_tuple=True)
            if len(sb):
                m = sub[sb, sr, sc].long()
                present = ((m[:, None] >> torch.arange(p)) & 1).bool()
                score = torch.where(present, rank[scenes][sb] + 1, torch.zeros((), dtype=torch.long))
                fixed = ids[scenes]
                fixed[sb, sr, sc] = score.argmax(1).to(torch.int8)
                ids[scenes] = fixed
    height = None
    if need_height:
        hlut = torch.cat([heights_t, torch.zeros(b, 1)], dim=1)
        height = torch.gather(hlut, 1, ids.reshape(b, -1).long() % (p + 1)).view(b, h, w)
    return Raster(ids, height)


def _mask_dtype(p: int) -> torch.dtype:
    if p <= 8:
        return torch.uint8
    if p <= 15:
        return torch.int16
    if p <= 31:
        return torch.int32
    if p <= 63:
        return torch.int64
    raise ValueError(f"the rasteriser handles at most 63 pieces per scene, got {p}")


def _highest_bit(mask: torch.Tensor) -> torch.Tensor:
    """Index of the highest set bit of non-negative integers (-1 for 0).

    Reads the exponent of the float conversion, exact for every integer that fits
    the float's mantissa: float16 for one-byte masks (half the memory traffic),
    float32 up to 2**24, float64 beyond.
    """
    if mask.dtype == torch.uint8:
        e = mask.to(torch.float16).view(torch.int16) >> 10
        e -= 15
    elif mask.dtype == torch.int64:
        e = mask.to(torch.float64).view(torch.int64) >> 52
        e -= 1023
    else:
        e = mask.to(torch.float32).view(torch.int32) >> 23
        e -= 127
    # Zero has a zero exponent field, i.e. minus the bias here.
    return e.clamp_(min=-1)
