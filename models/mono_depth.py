"""The photo layer's monocular depth network: photograph → frame 0's raw ray-distance channel (ours;
docs/DESIGN.md "Data flow of generate", step 6).

As single-image 3D systems take the observed pixels' geometry from a monocular depth network (Flash3D,
Szymanowicz et al. 2024), a small U-Net (Ronneberger et al. 2015) with a global-context 1×1 at its coarsest level
(ParseNet, Liu et al. 2015), trained on metric depth (``training.objectives``, objective ``depth``). Its output is
the LDRM's raw distance channel (before ``models.ldrm.gaussian_activations``); the last convolution starts at zero,
i.e. at the config's ``default_depth``. With ``grid`` = g > 0 the output is averaged over g×g cells and interpolated
back: the coarse layout only."""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

__all__ = ["MonoDepth"]


def _conv_block(c_in: int, c_out: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(c_in, c_out, 3, stride=stride, padding=1), nn.GELU(),
                         nn.Conv2d(c_out, c_out, 3, padding=1), nn.GELU())


class MonoDepth(nn.Module):
    """(B, 3, H, W) photograph in [−1, 1] → (B, H, W) raw ray-distance channel.

    Args:
        channels: C, the full-resolution width; level i has C·2^i channels at (H, W) / 2^i.
        levels: encoder stages (≥ 1); H and W must be divisible by 2^levels.
        grid: g > 0 averages the output over g×g cells; 0 keeps every pixel.

    Raises:
        ValueError: ``channels`` or ``levels`` < 1, ``grid`` < 0.
    """

    def __init__(self, channels: int, levels: int = 3, grid: int = 0) -> None:
        super().__init__()
        if channels < 1 or levels < 1 or grid < 0:
            raise ValueError(f"MonoDepth needs channels ≥ 1, levels ≥ 1 and grid ≥ 0, got {channels}, {levels}, {grid}")
        self.grid = grid
        widths = [channels * 2 ** i for i in range(levels + 1)]
        self.levels = levels
        self.stem = _conv_block(3, channels)
        self.down = nn.ModuleList(_conv_block(widths[i], widths[i + 1], stride=2) for i in range(levels))
        self.global_context = nn.Conv2d(widths[-1], widths[-1], 1)
        self.up = nn.ModuleList(_conv_block(widths[i + 1] + widths[i], widths[i]) for i in reversed(range(levels)))
        self.out = nn.Conv2d(channels, 1, 3, padding=1)
        nn.init.zeros_(self.out.weight)  # starts at the default depth everywhere (module docstring)
        nn.init.zeros_(self.out.bias)

    def forward(self, image: Tensor) -> Tensor:  # (B, 3, H, W) → (B, H, W)
        """Raw ray-distance channel (B, H, W) (a logit; metres after ``gaussian_activations``) of ``image`` (B, 3, H, W)
        in [−1, 1]. ValueError unless H and W are divisible by 2^levels."""
        f = 2 ** self.levels
        if image.dim() != 4 or image.shape[1] != 3 or image.shape[-2] % f or image.shape[-1] % f:
            raise ValueError(f"image must be (B, 3, H, W) with H and W divisible by {f}, got {tuple(image.shape)}")
        skips = [self.stem(image)]
        for down in self.down:
            skips.append(down(skips[-1]))
        y = skips.pop()
        y = y + self.global_context(y.mean(dim=(-2, -1), keepdim=True))  # every pixel sees the whole image
        for up in self.up:
            skip = skips.pop()
            y = up(torch.cat([F.interpolate(y, size=skip.shape[-2:], mode="bilinear", align_corners=False), skip], 1))
        y = self.out(y)
        if self.grid:  # the coarse layout only (module docstring)
            y = F.interpolate(F.adaptive_avg_pool2d(y, self.grid), size=y.shape[-2:], mode="bilinear",
                              align_corners=False)
        return y[:, 0]
