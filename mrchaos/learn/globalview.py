"""Global views for the spatial trunk: blocks that let every cell see the whole image.

The spatial net's fine layers see about 3 cm around a cell and its context path about 13 cm.
Where a piece goes in an edge-joined figure depends on the whole empty region it must share
with the pieces still to come, so these blocks give every cell the whole 120 x 120 image while
the head keeps its per-cell logits (``PolicyConfig.global_view``):

* ``attention``: the fine features cut into 2 x 2-cell patches (15 x 15 tokens over the view),
  with a learnt position embedding, through pre-norm transformer layers;
* ``unet``: an encoder down to 4 x 4 cells, where one 3 x 3 convolution spans the whole view,
  and a decoder back up with skip connections.

Both add their output to the fine features through a zero-initialised 1 x 1 convolution, so a
network starts as the one without the block and learns how much of the global view to use.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["GLOBAL_VIEWS", "build_global_view"]

#: The global blocks by name ("none": the spatial trunk as before).
GLOBAL_VIEWS = ("none", "attention", "unet")


def _zero_conv(cin: int, cout: int) -> nn.Conv2d:
    conv = nn.Conv2d(cin, cout, 1)
    nn.init.zeros_(conv.weight)
    nn.init.zeros_(conv.bias)  # type: ignore[arg-type]  # Conv2d has a bias unless told otherwise
    return conv


class PatchAttention(nn.Module):
    """Transformer layers over 2 x 2-cell patches of the fine features, added back per cell.

    Args:
        channels: the fine features' channels.
        width: the tokens' width.
        layers: transformer layers.
        cells: the fine lattice's side (30 for the 120-pixel view).
    """

    def __init__(self, channels: int, width: int, layers: int, cells: int) -> None:
        super().__init__()
        self.embed = nn.Conv2d(channels, width, 2, stride=2)
        side = (cells + 1) // 2
        self.position = nn.Parameter(torch.zeros(1, side * side, width))
        nn.init.trunc_normal_(self.position, std=0.02)
        layer = nn.TransformerEncoderLayer(
            width, max(1, width // 32), 2 * width, dropout=0.0, batch_first=True, norm_first=True
        )
        self.encoder = nn.TransformerEncoder(layer, layers, enable_nested_tensor=False)
        self.out = _zero_conv(width, channels)

    def forward(self, f: torch.Tensor) -> torch.Tensor:
        t = self.embed(f)
        b, w, h, x = t.shape
        tokens = self.encoder(t.flatten(2).transpose(1, 2) + self.position.to(t.dtype))
        t = tokens.transpose(1, 2).reshape(b, w, h, x)
        return F.interpolate(self.out(t), size=f.shape[-2:], mode="nearest")


class UNet(nn.Module):
    """An encoder (stride-2 steps from the fine lattice down to 4 x 4 cells, where a 3 x 3
    convolution sees the whole view) and a decoder back up, with skip connections.

    Args:
        channels: the fine features' channels.
        width: the encoder's first width (doubled once on the way down).
    """

    def __init__(self, channels: int, width: int) -> None:
        super().__init__()
        widths = [width, 2 * width, 2 * width]
        downs, cin = [], channels
        for w in widths:
            downs.append(nn.Conv2d(cin, w, 3, stride=2, padding=1))
            cin = w
        self.downs = nn.ModuleList(downs)
        self.bottom = nn.Conv2d(cin, cin, 3, padding=1)
        # Up: each step takes the coarser output and the encoder's skip at that scale.
        ups = []
        for skip in reversed([channels, *widths[:-1]]):
            cout = max(skip, width)
            ups.append(nn.Conv2d(cin + skip, cout, 3, padding=1))
            cin = cout
        self.ups = nn.ModuleList(ups)
        self.out = _zero_conv(cin, channels)

    def forward(self, f: torch.Tensor) -> torch.Tensor:
        skips, h = [], f
        for down in self.downs:
            skips.append(h)
            h = F.relu(down(h))
        h = F.relu(h + self.bottom(h))
        for up, skip in zip(self.ups, reversed(skips), strict=True):
            h = F.interpolate(h, size=skip.shape[-2:], mode="nearest")
            h = F.relu(up(torch.cat([h, skip], 1)))
        return self.out(h)


def build_global_view(name: str, channels: int, width: int, layers: int, cells: int) -> nn.Module | None:
    """The global block ``name`` (one of :data:`GLOBAL_VIEWS`) for fine features of ``channels``
    on a ``cells`` x ``cells`` lattice, or None for "none"."""
    if name == "none":
        return None
    if name == "attention":
        return PatchAttention(channels, width, layers, cells)
    if name == "unet":
        return UNet(channels, width)
    raise ValueError(f"policy.global_view must be one of {GLOBAL_VIEWS}, got {name!r}")
