"""The image branch's context path: a small U-Net (Ronneberger et al. 2015) over the photograph's features.

The LDRM's image branch (``models.ldrm.ImageBranch``) sees a 5×5-pixel window; the depth of a pixel on an object
standing on a floor depends on where the object meets the floor, tens of pixels away. The context path gives every
pixel a view of the whole image: ``levels`` stride-2 encoder stages doubling the channels (64² → 8² after three),
the image's mean feature added back at the coarsest level through a 1×1 convolution (the global context of ParseNet,
Liu et al. 2015: the convolutions alone reach about 40 pixels), a decoder of ×2 bilinear upsamplings each joined with
its encoder skip, and a last 1×1 convolution that is zero-initialised (weights and bias) so a new path adds exactly 0 and the branch
starts as the one without it (the zero convolution of ControlNet, Zhang et al. 2023; adaLN-Zero in DiT).
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

__all__ = ["ContextUNet"]


def _conv_block(c_in: int, c_out: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(c_in, c_out, 3, stride=stride, padding=1), nn.GELU(),
                         nn.Conv2d(c_out, c_out, 3, padding=1), nn.GELU())


class ContextUNet(nn.Module):
    """(B, C, H, W) → (B, C, H, W) residual features with a whole-image receptive field; 0 at initialisation.

    Args:
        channels: C, the image branch's width; level i (1…levels) has C·2^i channels at (H, W) / 2^i.
        levels: encoder stages (≥ 1); H and W must be divisible by 2^levels.

    Raises:
        ValueError: ``channels`` or ``levels`` < 1; (in forward) H or W not divisible by 2^levels.
    """

    def __init__(self, channels: int, levels: int) -> None:
        super().__init__()
        if channels < 1 or levels < 1:
            raise ValueError(f"ContextUNet needs channels ≥ 1 and levels ≥ 1, got {channels}, {levels}")
        widths = [channels * 2 ** i for i in range(levels + 1)]  # C, 2C, …, at full, 1/2, … resolution
        self.levels = levels
        self.down = nn.ModuleList(_conv_block(widths[i], widths[i + 1], stride=2) for i in range(levels))
        self.global_context = nn.Conv2d(widths[-1], widths[-1], 1)
        self.up = nn.ModuleList(_conv_block(widths[i + 1] + widths[i], widths[i]) for i in reversed(range(levels)))
        self.out = nn.Conv2d(channels, channels, 1)
        nn.init.zeros_(self.out.weight)  # zero convolution: a new path adds exactly 0 (module docstring)
        nn.init.zeros_(self.out.bias)

    def forward(self, x: Tensor) -> Tensor:  # (B, C, H, W) → (B, C, H, W)
        H, W = x.shape[-2:]
        f = 2 ** self.levels
        if H % f or W % f:
            raise ValueError(f"ContextUNet with {self.levels} levels needs H and W divisible by {f}, got {H}×{W}")
        skips = [x]
        for down in self.down:
            skips.append(down(skips[-1]))
        y = skips.pop()
        y = y + self.global_context(y.mean(dim=(-2, -1), keepdim=True))  # every pixel sees the whole image
        for up in self.up:
            skip = skips.pop()
            y = up(torch.cat([F.interpolate(y, size=skip.shape[-2:], mode="bilinear", align_corners=False), skip], 1))
        return self.out(y)
