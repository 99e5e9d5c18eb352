"""Rendering a (dynamic) Gaussian scene over time: along a camera path (:func:`render_path`, one frame per camera,
each at its time) and with a rolling shutter (:func:`render_rolling_shutter`, 4D-GRT's effect).

A rolling-shutter band of rows r0 … r1−1 is an image of height r1 − r0 with cy − r0, rendered by the ray path,
whose rays do not depend on the image extent (the rasterizer's Jacobian clamp does), so it equals those rows.
"""
from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor
from tqdm.auto import tqdm

from diff4splat.cameras.lenses import RollingShutter
from diff4splat.cameras.path import CameraPath
from diff4splat.render.rasterize import rasterize
from diff4splat.render.raytrace import raytrace
from diff4splat.render.settings import BACKGROUND
from diff4splat.render.sh import color_features
from diff4splat.scene.dynamic import DynamicGaussians

__all__ = ["render_path", "render_rolling_shutter"]


@torch.no_grad()
def render_path(
    scene: DynamicGaussians,
    cameras: CameraPath,
    *,
    background: tuple[float, float, float] = BACKGROUND,
    features: Tensor | None = None,
    progress: bool = False,
    **rasterize_kwargs,
) -> tuple[Tensor, Tensor, Tensor]:
    """Render frame i of ``cameras`` with the scene deformed to ``cameras.times[i]``, on the scene's device and dtype.

    Args:
        scene: canonical Gaussians (SH colours) + optional deformation; cameras: T cameras with times in [0, 1].
        background: RGB in [0, 1] behind the Gaussians; progress: tqdm progress bar over frames.
        features: (M, C) per-Gaussian channels (e.g. one-hot object ids) composited beside the colours over 0, in
            the same pass (the SH colours are then evaluated by :func:`~diff4splat.render.sh.color_features`).
        **rasterize_kwargs: passed to :func:`diff4splat.render.rasterize` (e.g. ``tile_size``, ``eps2d``); not
            ``render_mode`` ("RGB+ED"), ``backgrounds`` or ``sh_degree`` (the scene's), which are set here.

    Returns:
        colors (T, H, W, 3) in [0, 1] (clamped; with ``features`` (T, H, W, 3 + C), the features unclamped after
        the colours), expected depth (T, H, W) metres (0 where alpha = 0), alphas (T, H, W) in [0, 1]; on the
        scene's device.

    Raises:
        ValueError: as :func:`~diff4splat.render.rasterize`; ``features`` not (M, C).
    """
    dtype, device = scene.canonical.means.dtype, scene.canonical.means.device
    M, C = scene.num_gaussians, 0 if features is None else features.shape[-1]
    if features is not None and (features.dim() != 2 or features.shape[0] != M):
        raise ValueError(f"features must be (M, C) = ({M}, C), got {tuple(features.shape)}")
    bg = torch.tensor([[*background, *([0.0] * C)]], dtype=dtype, device=device)
    viewmats = cameras.viewmats.to(device=device, dtype=dtype)
    Ks = cameras.Ks.to(device=device, dtype=dtype)
    T, H, W = len(cameras), cameras.height, cameras.width
    for i in tqdm(range(T), desc="render", disable=not progress, leave=False):
        t = float(cameras.times[i])
        g = scene.at(t)
        colors_in, degree = g.sh, g.sh_degree
        if features is not None:  # the Gaussians at(t) keeps, in order, with their channels beside their colours
            kept = scene.active_indices(t)
            colors_in = torch.cat([color_features(g.sh, g.means, viewmats[i:i + 1], g.sh_degree)[0],
                                   (features if kept is None else features[kept]).to(device, dtype)], -1)
            degree = None
        out, alpha, _ = rasterize(g.means, g.quats, g.scales, g.opacities, colors_in, viewmats[i:i + 1],
                                  Ks[i:i + 1], W, H, sh_degree=degree, backgrounds=bg, render_mode="RGB+ED",
                                  **rasterize_kwargs)
        if i == 0:  # the outputs filled frame by frame (no stack of T frames): the renderer's dtype, the scene's device
            colors, depths = out.new_empty(T, H, W, 3 + C), out.new_empty(T, H, W)
            alphas = alpha.new_empty(T, H, W)
        torch.clamp(out[0, ..., :3], 0, 1, out=colors[i, ..., :3])
        colors[i, ..., 3:] = out[0, ..., 3:-1]
        depths[i], alphas[i] = out[0, ..., -1], alpha[0, ..., 0]
    return colors, depths, alphas


def render_rolling_shutter(
    scene: DynamicGaussians,
    cameras: CameraPath,
    shutter: RollingShutter,
    *,
    frames: Sequence[int] | None = None,
    interpolate_pose: bool = True,
    background: tuple[float, float, float] = BACKGROUND,
    **rasterize_kwargs,
) -> tuple[Tensor, Tensor, Tensor]:
    """Render frames of ``cameras`` with a rolling shutter (gradients flow to the scene tensors).

    Frame i (clip time ``cameras.times[i]``) reads row r at t(r) = t0 + (r + ½)/H · duration (t0 from
    ``shutter.anchor``; clamped to [0, 1]); each band of :meth:`~diff4splat.cameras.lenses.RollingShutter.row_bands`
    is rendered at the mean time of its rows with ``scene.at(t)`` and, with ``interpolate_pose``,
    ``cameras.viewmat_at(t)``, else frame i's viewmat; intrinsics are frame i's.

    Args:
        scene, cameras, background: as :func:`render_path`; shutter: readout duration (clip time), bands, anchor.
        frames: frame indices to render (default: all); interpolate_pose: move the camera during the readout.
        **rasterize_kwargs: passed to :func:`diff4splat.render.raytrace.raytrace` (not render_mode: "RGB+ED").

    Returns:
        colors (F, H, W, 3) clamped to [0, 1], expected z-depth (F, H, W) metres in each band's camera (0
        where alpha = 0), alphas (F, H, W); on the scene's device.

    Raises:
        ValueError: ``frames`` out of range, ``shutter.chunks`` > H, ``render_mode`` given, or as ``rasterize``.
    """
    if not isinstance(shutter, RollingShutter):
        raise ValueError(f"shutter must be a RollingShutter, got {type(shutter).__name__}")
    if "render_mode" in rasterize_kwargs:
        raise ValueError("render_mode is fixed to 'RGB+ED' in render_rolling_shutter")
    frames = list(range(len(cameras))) if frames is None else [int(f) for f in frames]
    for f in frames:
        if not 0 <= f < len(cameras):
            raise ValueError(f"frames holds {f}, outside 0..{len(cameras) - 1}")
    H, W = cameras.height, cameras.width
    bands = shutter.row_bands(H)
    dtype, device = scene.canonical.means.dtype, scene.canonical.means.device
    bg = torch.tensor([background], dtype=dtype, device=device)
    colors, depths, alphas = [], [], []
    for i in frames:
        K = cameras.Ks[i].to(device=device, dtype=dtype)
        rows_c, rows_a = [], []
        for (r0, r1), t in zip(bands, shutter.band_times(H, float(cameras.times[i])), strict=False):
            g = scene.at(t)
            vm = cameras.viewmat_at(t) if interpolate_pose else cameras.viewmats[i]
            K_band = K.clone()
            K_band[1, 2] = K[1, 2] - r0
            vm = vm.to(device=device, dtype=dtype)
            out, alpha, _ = raytrace(g.means, g.quats, g.scales, g.opacities, g.sh, vm[None], K_band[None],
                                     W, r1 - r0, sh_degree=g.sh_degree, backgrounds=bg, render_mode="RGB+ED",
                                     **rasterize_kwargs)
            rows_c.append(out[0])
            rows_a.append(alpha[0, ..., 0])
        img = torch.cat(rows_c, dim=0)
        colors.append(img[..., :3].clamp(0, 1))
        depths.append(img[..., 3])
        alphas.append(torch.cat(rows_a, dim=0))
    return torch.stack(colors), torch.stack(depths), torch.stack(alphas)
