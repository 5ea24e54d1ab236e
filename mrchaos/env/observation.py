"""Observation images: the silhouette prompt I_s and the current top-down view I_tc, as uint8.

The view is derived from the visible top-surface heights (a depth image seen
from above). ``binary`` thresholds it as the reference code did; ``levels`` keeps
a few height levels, one per piece thickness, so a piece stacked on another can be
told apart from one lying on the table.

``supersample`` k > 1 draws both images k times finer and averages each k x k block into one
pixel: a grey level that says how much of the pixel is covered. A binary pixel moves only when an
edge crosses its centre, so a shift under a pixel (the refined grid's 2.1 mm offsets under
cutlery's 3.3 mm pixels) is invisible to it; the grey level shows it. Rewards and metrics keep
the binary image at ``env.view.size``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from mrchaos.core.raster import Raster

__all__ = ["ObservationConfig", "view_image", "silhouette_image", "downsample"]

VIEW_MODES = ("binary", "levels")


@dataclass(frozen=True)
class ObservationConfig:
    """How the current view is encoded.

    Attributes:
        mode: "binary" (occupied = 255) or "levels" (height quantised to ``levels`` steps).
        levels: number of height levels in "levels" mode; level k means k piece
            thicknesses above the table, and the top level also takes anything higher.
        supersample: draw the silhouette and the view this many times finer and average each
            block into one grey pixel (1: the paper's binary pixels).
    """

    mode: str = "binary"
    levels: int = 3
    supersample: int = 1

    def __post_init__(self) -> None:
        if self.mode not in VIEW_MODES:
            raise ValueError(f"env.observation.mode must be one of {VIEW_MODES}, got {self.mode!r}")
        if self.levels < 1:
            raise ValueError(f"levels must be >= 1, got {self.levels}")
        if not 1 <= self.supersample <= 8:
            raise ValueError(f"env.observation.supersample must be 1..8, got {self.supersample}")

    @property
    def needs_height(self) -> bool:
        return self.mode == "levels"


def silhouette_image(target_ids: torch.Tensor) -> torch.Tensor:
    """(B, H, W) uint8 silhouette: 255 inside, 0 outside."""
    return (target_ids >= 0).to(torch.uint8) * 255


def view_image(raster: Raster, cfg: ObservationConfig, thickness: float = 0.010) -> torch.Tensor:
    """(B, H, W) uint8 current view from a raster of the placed pieces; one level is ``thickness`` metres."""
    occ = raster.ids >= 0
    if cfg.mode == "binary":
        return occ.to(torch.uint8) * 255
    assert raster.height is not None, "the levels view needs the raster's heights (need_height)"
    level = torch.ceil(raster.height / thickness - 0.25).clamp(1, cfg.levels)
    return torch.where(occ, (level * (255.0 / cfg.levels)).round(), torch.zeros(())).to(torch.uint8)


def downsample(image: torch.Tensor, k: int) -> torch.Tensor:
    """(B, kH, kW) uint8 image averaged over k x k blocks into (B, H, W) uint8 (k = 1: unchanged)."""
    if k == 1:
        return image
    grey = torch.nn.functional.avg_pool2d(image[:, None].float(), k)[:, 0]
    return grey.round().to(torch.uint8)
