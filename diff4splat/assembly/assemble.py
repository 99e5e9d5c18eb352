"""From the LDRM's maps to a 4D scene (docs/DESIGN.md, "Data flow of generate", step 7).

:func:`assemble_scene` puts the photo layer (:mod:`diff4splat.assembly.photo`: the photograph at the output
resolution on the reference grid's upsampled depth, its deformation re-based to the photograph's time), the
static backdrop, then the network's pixel-aligned Gaussians of source frames 1…S−1 at the model resolution
(optionally coloured by the decoded video, :func:`video_colors`, and made pixel disks, :func:`pixel_footprint`).
Order: the photo layer's H_o·W_o front then ⌈H_o/2⌉·⌈W_o/2⌉ backing disks, the backdrop, then h·w per source
frame 1…S−1, each row-major.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from diff4splat.assembly.photo import (
    PHOTO_EPS2D,
    PHOTO_OPACITY,
    backdrop_layer,
    check_photo_fidelity,
    photo_layer,
    pixel_disks,
    upsample_depth,
)
from diff4splat.cameras import CameraPath, camera_rays
from diff4splat.geometry.depth_alignment import fit_scale_shift
from diff4splat.io.depth_maps import valid_depth
from diff4splat.scene.dynamic import DynamicGaussians
from diff4splat.scene.gaussians import Gaussians, rgb_to_sh0
from diff4splat.scene.quaternions import quat_conjugate, quat_multiply, quat_normalize
from diff4splat.utils.devices import autocast_off
from models.bundle import GENERATED_FOOTPRINTS
from models.deformation import IDENTITY_QUAT
from models.ldrm import LDRMOutput

__all__ = ["DEPTH_KINDS", "GENERATED_SCALE_PX", "to_gaussians", "video_colors", "pixel_footprint", "photo_depth",
           "rebase_deformation", "assemble_scene", "z_depth"]

DEPTH_KINDS = ("metric", "relative", "inverse")
"""What a user's depth map holds (``--depth-kind``): metric z-depth (metres, used as given), relative depth or
relative inverse depth (affine in z or 1/z, fitted to the network's depth by least squares)."""
GENERATED_SCALE_PX = 0.7
"""In-plane σ, pixels at its source camera, of a generated frame's disk under :func:`pixel_footprint`: tiles the
frame at any output magnification (alpha ≥ 0.98 at the corner between four pixels; docs/DESIGN.md, step 7)."""


def to_gaussians(
    out: LDRMOutput,
    viewmats: Tensor,  # (S, 4, 4) world-to-camera of the source frames
    Ks: Tensor,  # (S, 3, 3) pixels
    batch_index: int = 0,
) -> tuple[Gaussians, Tensor | None, Tensor | None, Tensor | None]:
    """Pixel-aligned Gaussians, one per pixel of each source frame of ``out`` (B, S, H, W, ·), and its deformation
    flattened to d_means (K, M, 3), d_quats (K, M, 4), d_scales (K, M, 3) (or None), M = S·H·W.

    Gaussian s·H·W + y·W + x sits at μ = o + distance·d on the pixel-centre ray of pixel (x, y) of source camera s
    (:func:`diff4splat.cameras.camera_rays`); colours clamped to [1e-4, 1 − 1e-4], stored as SH degree 0. Float32 at
    least, computed with autocast off.

    Raises:
        ValueError: ``viewmats``/``Ks`` not (S, 4, 4)/(S, 3, 3), or ``batch_index`` out of range.
    """
    B, S, H, W = out.distance.shape
    if not -B <= batch_index < B:
        raise ValueError(f"batch_index {batch_index} out of range for batch size {B}")
    if tuple(viewmats.shape) != (S, 4, 4):
        raise ValueError(f"viewmats must have shape ({S}, 4, 4) (one per source frame), got {tuple(viewmats.shape)}")
    if tuple(Ks.shape) != (S, 3, 3):
        raise ValueError(f"Ks must have shape ({S}, 3, 3) (one per source frame), got {tuple(Ks.shape)}")
    dtype = torch.promote_types(out.distance.dtype, torch.float32)
    get = lambda name: getattr(out, name)[batch_index].to(dtype)  # noqa: E731
    with autocast_off():
        origins, dirs = camera_rays(viewmats.to(dtype), Ks.to(dtype), W, H)  # (S, H, W, 3)
        means = origins + get("distance")[..., None] * dirs
        colors = get("colors").clamp(1e-4, 1 - 1e-4)
        M = S * H * W
        gaussians = Gaussians(
            means=means.reshape(M, 3),
            quats=get("quats").reshape(M, 4),
            scales=get("scales").reshape(M, 3),
            opacities=get("opacities").reshape(M),
            sh=rgb_to_sh0(colors).reshape(M, 1, 3),
        )
    if out.d_means is None:
        return gaussians, None, None, None
    flat = [get(f).flatten(1, 3) for f in ("d_means", "d_quats", "d_scales")]
    return gaussians, *flat


def _align(user: Tensor, network: Tensor, kind: str) -> Tensor:
    """``user`` (H, W) aligned to ``network`` (H, W) metres by kind (:data:`DEPTH_KINDS`); non-finite where invalid."""
    if kind == "metric":
        return user
    valid = torch.isfinite(user)  # the holes are NaN (photo_depth)
    x = user.detach().double().cpu().numpy()  # device: depth_alignment fits in numpy; result moved back
    y = network.detach().double().cpu().numpy()  # device: as above
    mask = valid.cpu().numpy()  # device: as above
    fit = fit_scale_shift(x, y, mask, space="depth" if kind == "relative" else "disparity")
    return torch.from_numpy(fit.apply(np.where(mask, x, np.nan))).to(user)


def photo_depth(
    distance: Tensor,  # (h, w) metres along the reference rays, model resolution
    viewmat: Tensor,  # (4, 4)
    K: Tensor,  # (3, 3) at the model resolution
    image: Tensor,  # (H, W, 3) the photograph at the output resolution
    depth: Tensor | None = None,  # (H, W) the user's depth map
    depth_kind: str = "metric",
) -> Tensor:
    """The photo layer's z-depth at the output resolution, (H, W) metres, finite and > 0, on ``image``'s device.

    The network's ray distance × cos(angle to the optical axis), upsampled by
    :func:`diff4splat.assembly.photo.upsample_depth` with the photograph as the guide; or a user's ``depth``,
    aligned by ``depth_kind`` (:data:`DEPTH_KINDS`, ``diff4splat.geometry.depth_alignment.fit_scale_shift``), its
    holes (:func:`diff4splat.io.depth_maps.valid_depth`) filled with the network's depth.

    Raises:
        ValueError: ``depth`` not (H, W); an unknown ``depth_kind``; a degenerate fit (a negative scale).
    """
    if depth_kind not in DEPTH_KINDS:
        raise ValueError(f"depth_kind must be one of {DEPTH_KINDS}, got {depth_kind!r}")
    H, W = image.shape[:2]
    z_net = upsample_depth(z_depth(distance[None], viewmat[None], K[None])[0], image)
    if depth is None:
        return z_net
    if tuple(depth.shape) != (H, W):
        raise ValueError(f"depth must have shape ({H}, {W}) (the output resolution), got {tuple(depth.shape)}")
    depth = depth.to(z_net)
    aligned = _align(torch.where(valid_depth(depth, depth_kind), depth, torch.nan), z_net, depth_kind)
    return torch.where(valid_depth(aligned, "metric"), aligned, z_net)


def z_depth(distance: Tensor, viewmats: Tensor, Ks: Tensor) -> Tensor:
    """Z-depth maps (S, h, w) of ray-distance maps (S, h, w) (metres along each pixel's unit ray) seen by cameras
    ``viewmats`` (S, 4, 4), ``Ks`` (S, 3, 3) at (h, w): distance × cos(angle to the optical axis); float32 at least."""
    S, h, w = distance.shape
    dtype = torch.promote_types(distance.dtype, torch.float32)
    _, dirs = camera_rays(viewmats.to(dtype), Ks.to(dtype), w, h)  # (S, h, w, 3) world
    return distance.to(dtype) * torch.einsum("shwc,sc->shw", dirs, viewmats[:, 2, :3].to(dtype))


def rebase_deformation(d_means: Tensor, d_quats: Tensor, d_scales: Tensor, reference: tuple[Tensor, Tensor, Tensor]
                       ) -> tuple[Tensor, Tensor, Tensor]:
    """Deformations (K, M, ·) made relative to ``reference`` (M, ·), the deformation at the photograph's time:
    Δμ' = Δμ − Δμ₀, Δq' = Δq ⊗ Δq₀⁻¹, Δs' = Δs − Δs₀, so the deformed Gaussians at that time are the canonical ones
    exactly (docs/DESIGN.md, "Deformation at time t": q_t = Δq ⊗ q)."""
    m0, q0, s0 = reference
    q0 = quat_normalize(q0, "d_quats")
    return d_means - m0, quat_multiply(quat_normalize(d_quats, "d_quats"), quat_conjugate(q0)), d_scales - s0


def video_colors(
    out: LDRMOutput,
    video: Tensor,  # (1, 3, T, h, w) the decoded generated video, about [−1, 1]
    sources: Tensor,  # (S,) video frame of each source frame
) -> LDRMOutput:
    """``out`` with source frames 1…'s colours replaced by the decoded video's pixels (clamped) at those frames (the
    photo layer's rule for generated frames: keep what the generator drew); every other map is shared. ``out``'s
    colours are (1, S, h, w, 3) in [0, 1], ``video`` (1, 3, T, h, w) with T > max(``sources``).

    Raises:
        ValueError: ``video`` not (1, 3, T, h, w) at the maps' grid, or a source frame outside it.
    """
    S, h, w = out.colors.shape[1:4]
    if video.dim() != 5 or tuple(video.shape[:2]) != (1, 3) or tuple(video.shape[-2:]) != (h, w):
        raise ValueError(f"video must have shape (1, 3, T, {h}, {w}), got {tuple(video.shape)}")
    if len(sources) != S or int(sources.max()) >= video.shape[2]:
        raise ValueError(f"sources {sources.tolist()} must name {S} frames of the video's {video.shape[2]}")
    frames = ((video[0, :, sources.to(video.device)].permute(1, 2, 3, 0) + 1) / 2).clamp(0, 1)  # (S, h, w, 3)
    colors = torch.cat([out.colors[:, :1], frames[None, 1:].to(out.colors)], dim=1)
    return dataclasses.replace(out, colors=colors)


def pixel_footprint(
    gaussians: Gaussians,  # (S·h·w) one per pixel of S source frames, camera-major then row-major (to_gaussians)
    viewmats: Tensor,  # (S, 4, 4) world-to-camera of the source frames
    Ks: Tensor,  # (S, 3, 3) pixels, at h × w
    width: int,
    height: int,
) -> Gaussians:
    """``gaussians`` as opaque disks facing their source camera: in-plane σ = :data:`GENERATED_SCALE_PX` pixels at their
    own z-depth (:func:`diff4splat.assembly.photo.pixel_disks`), opacity
    :data:`~diff4splat.assembly.photo.PHOTO_OPACITY`;
    means and colours unchanged. Each source frame rendered alone at its camera then covers itself edge to edge.

    Raises:
        ValueError: not S·height·width Gaussians for the S cameras, or a Gaussian at or behind its camera's plane.
    """
    S = viewmats.shape[0]
    if gaussians.num_gaussians != S * height * width or tuple(Ks.shape) != (S, 3, 3):
        raise ValueError(f"expected {S}·{height}·{width} Gaussians and Ks of shape ({S}, 3, 3), got "
                         f"{gaussians.num_gaussians} and {tuple(Ks.shape)}")
    means = gaussians.means.reshape(S, height * width, 3)
    viewmats = viewmats.to(means)
    z = (means * viewmats[:, None, 2, :3]).sum(-1) + viewmats[:, None, 2, 3]  # (S, h·w) z-depth at its camera
    if not bool((z > 0).all()):
        raise ValueError("every Gaussian must lie in front of its source camera (z-depth > 0)")
    _, quats, scales = pixel_disks(viewmats, Ks, width, height, z.reshape(S, height, width), GENERATED_SCALE_PX)
    opacities = torch.full_like(gaussians.opacities, PHOTO_OPACITY)
    return Gaussians(gaussians.means, quats, scales, opacities, gaussians.sh)


def assemble_scene(
    out: LDRMOutput,
    sources: Tensor,  # (S,) video frame of each source frame
    cameras_model: CameraPath,  # the path at the model resolution (h × w)
    cameras: CameraPath,  # the path at the output resolution (W × H)
    image: Tensor,  # (H, W, 3) in [0, 1], the photograph at the output resolution
    times: Tensor | None,  # (K,) key times of the deformation maps, or None (static)
    *,
    depth: Tensor | None = None,
    depth_kind: str = "metric",
    eps2d: float = PHOTO_EPS2D,
    video: Tensor | None = None,
    footprint: str = "ldrm",
) -> tuple[DynamicGaussians, Tensor, dict]:
    """The scene of one generation (module docstring).

    ``out``: the LDRM's maps for batch 1, deformation (1, K, S, h, w, ·) or None; ``sources[0]`` = 0, the photograph;
    ``depth``, ``depth_kind``: a user's depth map (:func:`photo_depth`); ``eps2d``: the render's dilation, pixels²;
    ``video``: the decoded video for :func:`video_colors`, or None; ``footprint``: ``"ldrm"`` or ``"pixel"``
    (:func:`pixel_footprint`).

    Returns:
        (scene, source (M,) long: each Gaussian's source frame, 0 for the photo layer and backdrop, stats dict:
        ``photo_psnr_db``, ``photo_gaussians``, ``backdrop_gaussians``, ``photo_depth`` (H, W) metres and
        ``background``, the photograph's mean RGB in [0, 1]).

    Raises:
        ValueError: as :func:`photo_depth`, :func:`~diff4splat.assembly.photo.photo_layer`, :func:`video_colors` and
            :func:`pixel_footprint`; an unknown ``footprint``; a photo layer that does not render the photograph
            (:func:`~diff4splat.assembly.photo.check_photo_fidelity`).
    """
    if footprint not in GENERATED_FOOTPRINTS:
        raise ValueError(f"footprint must be one of {GENERATED_FOOTPRINTS}, got {footprint!r}")
    if video is not None:
        out = video_colors(out, video, sources)
    S, h, w = out.distance.shape[1:4]
    H, W = image.shape[:2]
    dev = image.device
    # The deformation is left out of to_gaussians: written below straight into the scene's tensors.
    gaussians, *_ = to_gaussians(dataclasses.replace(out, d_means=None, d_quats=None, d_scales=None),
                                 cameras_model.viewmats[sources], cameras_model.Ks[sources])
    z = photo_depth(out.distance[0, 0], cameras_model.viewmats[0], cameras_model.Ks[0], image, depth, depth_kind)
    viewmat, K0 = cameras.viewmats[0].float(), cameras.Ks[0].float()
    layer, history = photo_layer(image, z, viewmat, K0, eps2d=eps2d)
    check_photo_fidelity(history[-1])  # frame 0 is the photograph, or nothing is written
    backdrop = backdrop_layer(image, z, viewmat, K0)
    n_photo, n_back, n_grid = layer.num_gaussians, backdrop.num_gaussians, h * w
    generated = gaussians.select(torch.arange(n_grid, S * n_grid, device=dev))
    if footprint == "pixel" and S > 1:
        generated = pixel_footprint(generated, cameras_model.viewmats[sources[1:]], cameras_model.Ks[sources[1:]], w, h)
    canonical = Gaussians(*(torch.cat([getattr(layer, f), getattr(backdrop, f), getattr(generated, f)])
                            for f in ("means", "quats", "scales", "opacities", "sh")))
    source = torch.cat([torch.zeros(n_photo + n_back, dtype=torch.long, device=dev),
                        torch.arange(1, S, device=dev).repeat_interleave(n_grid)])
    stats = {"photo_psnr_db": history[-1], "photo_gaussians": n_photo, "backdrop_gaussians": n_back,
             "photo_depth": z, "background": tuple(float(c) for c in image.reshape(-1, 3).mean(0))}
    if out.d_means is None:
        return DynamicGaussians(canonical), source, stats
    reference_grid = gaussians.select(torch.arange(n_grid, device=dev))
    deform = _deformation(out, reference_grid, times, float(cameras.times[0]), (H, W), n_back)
    return DynamicGaussians(canonical, times, *deform), source, stats


def _deformation(out: LDRMOutput, grid: Gaussians, times: Tensor, t0: float, size: tuple[int, int],
                 n_back: int) -> list[Tensor]:
    """The scene's (d_means, d_quats, d_scales), (K, N, ·), in :func:`assemble_scene`'s order, filled in place."""
    raw = [getattr(out, f)[0] for f in ("d_means", "d_quats", "d_scales")]  # (K, S, h, w, c)
    K, S, h, w = raw[0].shape[:4]
    dtype = torch.promote_types(out.distance.dtype, torch.float32)
    ref = DynamicGaussians(grid, times, *(m[:, 0].reshape(K, h * w, -1).to(dtype) for m in raw))
    ref = rebase_deformation(ref.d_means, ref.d_quats, ref.d_scales, ref.deformation_at(t0))
    size_back = (-(-size[0] // 2), -(-size[1] // 2))  # the backing disks' half-resolution grid
    n_photo = size[0] * size[1] + size_back[0] * size_back[1]
    deform = []
    for m, r, identity in zip(raw, ref, ((0.0,) * 3, IDENTITY_QUAT, (0.0,) * 3), strict=True):
        c = len(identity)
        d = torch.empty(K, n_photo + n_back + (S - 1) * h * w, c, device=grid.means.device, dtype=dtype)
        start = 0
        for grid_size in (size, size_back):
            n = grid_size[0] * grid_size[1]
            up = F.interpolate(r.reshape(K, h, w, c).permute(0, 3, 1, 2), size=grid_size, mode="bilinear",
                               align_corners=False)  # (K, c, H, W)
            d[:, start:start + n] = up.permute(0, 2, 3, 1).reshape(K, n, c)
            start += n
        d[:, n_photo:n_photo + n_back] = torch.tensor(identity, dtype=dtype, device=d.device)
        d[:, n_photo + n_back:].view(K, S - 1, h, w, c).copy_(m[:, 1:])  # converts the dtype while copying
        deform.append(d)
    return deform
