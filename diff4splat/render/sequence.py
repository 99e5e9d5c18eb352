"""Rendering a (dynamic) Gaussian scene along a camera path: one frame per camera, each at its time."""
from __future__ import annotations

import torch
from torch import Tensor
from tqdm.auto import tqdm

from ..cameras.path import CameraPath
from ..scene import DynamicGaussians
from .defaults import BACKGROUND
from .rasterize import rasterize

__all__ = ["render_path"]


@torch.no_grad()
def render_path(
    scene: DynamicGaussians,
    cameras: CameraPath,
    *,
    background: tuple[float, float, float] = BACKGROUND,
    progress: bool = False,
    **rasterize_kwargs,
) -> tuple[Tensor, Tensor, Tensor]:
    """Render frame i of ``cameras`` with the scene deformed to ``cameras.times[i]``.

    Runs on the scene's device (that of ``scene.canonical.means``): the path's viewmats and Ks are moved
    there (and cast to the scene's dtype), the background is made there; :func:`~diff4splat.render.rasterize`
    picks the path (gsplat or the PyTorch tile path on CUDA, the fused path on the CPU).

    Args:
        scene: canonical Gaussians + optional deformation (SH colours).
        cameras: T cameras (OpenCV world-to-camera) with times in [0, 1].
        background: RGB in [0, 1] behind the Gaussians.
        progress: tqdm progress bar over frames.
        **rasterize_kwargs: passed to :func:`diff4splat.render.rasterize` (e.g. ``tile_size``, ``eps2d``: a
            generated scene's own is ``GenerationResult.eps2d``); not ``render_mode`` ("RGB+ED"), ``backgrounds``
            (from ``background``) or ``sh_degree`` (the scene's), which are set here.

    Returns:
        colors (T, H, W, 3) in [0, 1] (clamped), expected depth (T, H, W) metres (0 where alpha = 0),
        alphas (T, H, W) in [0, 1]; on the scene's device.

    Raises:
        ValueError: as :func:`~diff4splat.render.rasterize`.
    """
    dtype, device = scene.canonical.means.dtype, scene.canonical.means.device
    bg = torch.tensor([background], dtype=dtype, device=device)
    viewmats = cameras.viewmats.to(device=device, dtype=dtype)
    Ks = cameras.Ks.to(device=device, dtype=dtype)
    colors, depths, alphas = [], [], []
    for i in tqdm(range(len(cameras)), desc="render", disable=not progress, leave=False):
        g = scene.at(float(cameras.times[i]))
        out, alpha, _ = rasterize(g.means, g.quats, g.scales, g.opacities, g.sh, viewmats[i:i + 1],
                                  Ks[i:i + 1], cameras.width, cameras.height,
                                  sh_degree=g.sh_degree, backgrounds=bg, render_mode="RGB+ED", **rasterize_kwargs)
        colors.append(out[0, ..., :3].clamp(0, 1))
        depths.append(out[0, ..., 3])
        alphas.append(alpha[0, ..., 0])
    return torch.stack(colors), torch.stack(depths), torch.stack(alphas)
