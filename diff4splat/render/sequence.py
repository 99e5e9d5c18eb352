"""Rendering a (dynamic) Gaussian scene over time: along a camera path (:func:`render_path`, one frame per camera,
each at its time), and with a rolling shutter (:func:`render_rolling_shutter`).

Rolling shutter (4D-GRT's rolling-shutter effect): each band of rows
(:meth:`diff4splat.cameras.lenses.RollingShutter.row_bands`) is rendered with the scene deformed to the band's
capture time and, optionally, the camera pose interpolated along the path to that time
(:meth:`diff4splat.cameras.CameraPath.viewmat_at`); the bands are stacked into the frame. A band of rows r0 … r1−1
is rendered as an image of height r1 − r0 whose principal point is shifted up by r0 pixels (cy − r0), so its pixel
centres are exactly those rows of the full image. Bands are rendered by the ray path
(:func:`diff4splat.render.raytrace.raytrace`, every camera model and effect), whose rays do not depend on the image
extent, so a band equals its rows of the full frame exactly. (The tile rasterizer would not do: its EWA Jacobian
clamp at 1.3× the field of view, as in gsplat, depends on the image height and cy, so a one-row band would distort
every splat.) Chunks = 1 is one ordinary ray-traced frame.
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
from diff4splat.scene.dynamic import DynamicGaussians

__all__ = ["render_path", "render_rolling_shutter"]


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
    """Render frames of ``cameras`` with a rolling shutter.

    Frame i (clip time t_i = ``cameras.times[i]``) reads row r at
    t(r) = t0 + (r + ½)/H · duration (t0 from ``shutter.anchor``; clamped to [0, 1]); band k of
    ``shutter.chunks`` is rendered at the mean time of its rows with ``scene.at(t)`` and, with
    ``interpolate_pose``, ``cameras.viewmat_at(t)`` (centre lerp + rotation nlerp between the path's
    cameras), else with frame i's own viewmat. Intrinsics are frame i's. Gradients flow to the
    scene tensors (no ``no_grad`` here).

    Args:
        scene: canonical Gaussians (SH colours) + optional deformation.
        cameras: T cameras with clip times.
        shutter: readout duration (clip-time units), number of row bands, anchor.
        frames: frame indices to render (default: all).
        interpolate_pose: move the camera along the path during the readout.
        background: RGB in [0, 1] behind the Gaussians.
        **rasterize_kwargs: passed to :func:`diff4splat.render.raytrace.raytrace` (camera_model,
            camera_params, tile_size, near_plane, …; not render_mode, which is "RGB+ED").

    Returns:
        colors (F, H, W, 3) clamped to [0, 1], expected z-depth (F, H, W) metres in each band's camera (0
        where alpha = 0), alphas (F, H, W); on the scene's device.

    Raises:
        ValueError: ``frames`` out of range, ``shutter.chunks`` > H, ``render_mode`` in
            ``rasterize_kwargs``, or as ``rasterize``.
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
