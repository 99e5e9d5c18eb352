"""Dense brute-force reference rasterizer: the oracle the fast tile path is tested against.

:func:`rasterize_dense` evaluates every Gaussian at every pixel (a (pixels × Gaussians) alpha
matrix), sorts the Gaussians globally by depth and composites them one after the other exactly as
gsplat's ``rasterize_to_pixels`` kernel loop does. It is slow (O(H·W·N) memory) and meant for
tests and tiny images. The fast tile rasterizer (:mod:`diff4splat.render.rasterize`) runs the same
pipeline (:func:`diff4splat.render.stages.render_pipeline`: input checks, projection, colours/depth
channels, render modes, meta), so the two differ only in how Gaussians are composited.
"""
from __future__ import annotations

import torch
from torch import Tensor

from diff4splat.constants import T_MIN
from diff4splat.render.defaults import (
    CAMERA_MODEL,
    EPS2D,
    FAR_PLANE,
    NEAR_PLANE,
    RASTERIZE_MODE,
    RENDER_MODE,
    SH_DEGREE,
    TILE_SIZE,
)
from diff4splat.render.projection import splat_alpha
from diff4splat.render.settings import RasterSettings
from diff4splat.render.stages import render_pipeline

__all__ = ["rasterize_dense", "composite_dense"]


def composite_dense(
    means2d: Tensor,  # (M, 2)
    conics: Tensor,  # (M, 3)
    opacities: Tensor,  # (M,)
    depths: Tensor,  # (M,)
    feats: Tensor,  # (M, F)
    covars2d: Tensor,  # (M, 3), unused: every pixel is evaluated
    background: Tensor | None,  # (F,)
    width: int,
    height: int,
    tile_size: int,  # unused: no tiles
) -> tuple[Tensor, Tensor, dict]:
    """Composite one camera by brute force: all pixels × all Gaussians, sequential in depth.

    Gaussians are sorted by depth (stable, ties keep input order). For each pixel, T = 1; for each
    Gaussian front to back with alpha from :func:`splat_alpha` (0 = skipped): next_T = T·(1 − alpha);
    if next_T < 1e-4 the pixel stops and this Gaussian is not included; otherwise the pixel gains
    alpha·T·feat and T = next_T. Finally colour += T·background, alpha = 1 − T (gsplat
    ``rasterize_to_pixels_fwd``; 3DGS eq. 3).

    The loop runs over the depth-sorted Gaussians (this is the brute-force oracle, for tests and tiny
    images); every tensor is made on the device of ``means2d``, so it runs on any device.

    Returns:
        colors: (H·W, F), alphas: (H·W,), info {} (no tiles).
    """
    dtype, device = means2d.dtype, means2d.device
    order = torch.argsort(depths, stable=True)
    ys, xs = torch.meshgrid(
        torch.arange(height, dtype=dtype, device=device) + 0.5, torch.arange(width, dtype=dtype, device=device) + 0.5,
        indexing="ij",
    )
    px, py = xs.reshape(-1, 1), ys.reshape(-1, 1)  # (P, 1)
    m2, cn, op, ft = means2d[order], conics[order], opacities[order], feats[order]
    alphas = splat_alpha(px - m2[None, :, 0], py - m2[None, :, 1], cn[None], op[None])  # (P, M)
    n_pix = px.shape[0]
    T = torch.ones(n_pix, dtype=dtype, device=device)
    done = torch.zeros(n_pix, dtype=torch.bool, device=device)
    out = torch.zeros(n_pix, feats.shape[-1], dtype=dtype, device=device)
    for i in range(alphas.shape[1]):
        a = alphas[:, i]
        next_T = T * (1.0 - a)
        live = ~done & (a > 0)
        stop = live & (next_T < T_MIN)
        take = live & ~stop
        done = done | stop
        w = torch.where(take, a * T, torch.zeros_like(a))
        out = out + w[:, None] * ft[i]
        T = torch.where(take, next_T, T)
    if background is not None:
        out = out + T[:, None] * background
    return out, 1.0 - T, {}


def rasterize_dense(
    means: Tensor,  # (N, 3)
    quats: Tensor,  # (N, 4)
    scales: Tensor,  # (N, 3)
    opacities: Tensor,  # (N,)
    colors: Tensor,  # (N, D) or (N, K, 3) with sh_degree
    viewmats: Tensor,  # (C, 4, 4)
    Ks: Tensor,  # (C, 3, 3)
    width: int,
    height: int,
    *,
    near_plane: float = NEAR_PLANE,
    far_plane: float = FAR_PLANE,
    eps2d: float = EPS2D,
    sh_degree: int | None = SH_DEGREE,
    backgrounds: Tensor | None = None,
    render_mode: str = RENDER_MODE,
    rasterize_mode: str = RASTERIZE_MODE,
    camera_model: str = CAMERA_MODEL,
    tile_size: int = TILE_SIZE,
) -> tuple[Tensor, Tensor, dict]:
    """Brute-force reference renderer; same arguments and outputs as :func:`diff4splat.render.rasterize`.

    Every visible Gaussian is evaluated at every pixel (memory O(H·W·N)) and composited by
    :func:`composite_dense`. Use for tests and tiny images only; ``tile_size`` is accepted for
    signature compatibility and only reported in ``meta``.

    Returns:
        render_colors (C, H, W, D[+1]), render_alphas (C, H, W, 1), meta (see ``rasterize``).

    Raises:
        ValueError: as :func:`diff4splat.render.rasterize`.
    """
    settings = RasterSettings(near_plane=near_plane, far_plane=far_plane, eps2d=eps2d, sh_degree=sh_degree,
                              backgrounds=backgrounds, render_mode=render_mode, rasterize_mode=rasterize_mode,
                              camera_model=camera_model, tile_size=tile_size)
    return render_pipeline(composite_dense, means, quats, scales, opacities, colors, viewmats, Ks, width, height,
                           settings)
