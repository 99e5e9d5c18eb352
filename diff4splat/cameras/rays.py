"""Per-pixel camera rays and Plücker embeddings (CameraCtrl / AC3D / MoVieS convention)."""
from __future__ import annotations

import torch
from torch import Tensor

from diff4splat.cameras.path import camera_centers

__all__ = ["camera_rays", "plucker_rays", "pack_plucker", "unproject_depth"]


def camera_rays(
    viewmats: Tensor,  # (C, 4, 4) world-to-camera
    Ks: Tensor,  # (C, 3, 3) pixels
    width: int,
    height: int,
) -> tuple[Tensor, Tensor]:
    """World-frame origins (C, H, W, 3), metres, and unit directions (C, H, W, 3) of every pixel's pinhole ray: pixel
    (i, j) at (j+0.5, i+0.5), d = normalise(Rᵀ K⁻¹ (u, v, 1)ᵀ), o = −Rᵀ t for viewmat [R | t].

    Raises:
        ValueError: ``viewmats`` not (C, 4, 4) or ``Ks`` not (C, 3, 3).
    """
    if viewmats.dim() != 3 or viewmats.shape[1:] != (4, 4):
        raise ValueError(f"viewmats must have shape (C, 4, 4), got {tuple(viewmats.shape)}")
    if Ks.shape != (viewmats.shape[0], 3, 3):
        raise ValueError(f"Ks must have shape ({viewmats.shape[0]}, 3, 3), got {tuple(Ks.shape)}")
    dtype, device = viewmats.dtype, viewmats.device
    v, u = torch.meshgrid(
        torch.arange(height, dtype=dtype, device=device) + 0.5,
        torch.arange(width, dtype=dtype, device=device) + 0.5,
        indexing="ij",
    )
    pix = torch.stack([u, v, torch.ones_like(u)], dim=-1)  # (H, W, 3)
    d_cam = torch.einsum("cij,hwj->chwi", torch.linalg.inv(Ks.to(dtype)), pix)
    R = viewmats[:, :3, :3]
    d_world = torch.einsum("cji,chwj->chwi", R, d_cam)  # Rᵀ d
    d_world = d_world / d_world.norm(dim=-1, keepdim=True)
    centres = camera_centers(viewmats)  # −Rᵀ t, (C, 3)
    origins = centres[:, None, None, :].expand_as(d_world)
    return origins, d_world


def unproject_depth(
    viewmats: Tensor,  # (C, 4, 4) world-to-camera
    Ks: Tensor,  # (C, 3, 3) pixels
    depth: Tensor,  # (C, H, W) z-depth, metres
) -> Tensor:
    """World points (C, H, W, 3), metres, of every pixel at its z-depth: p = o + d·z / (d · ẑ) with o, d the ray of
    :func:`camera_rays` and ẑ the optical axis (= Rᵀ(z·K⁻¹(u, v, 1)ᵀ − t)). Non-finite depths give non-finite points.

    Raises:
        ValueError: shapes that do not match (C, 4, 4), (C, 3, 3), (C, H, W).
    """
    if depth.dim() != 3 or depth.shape[0] != viewmats.shape[0]:
        raise ValueError(f"depth must have shape ({viewmats.shape[0]}, H, W), got {tuple(depth.shape)}")
    o, d = camera_rays(viewmats, Ks, depth.shape[2], depth.shape[1])
    axis = viewmats[:, 2, :3].to(d.dtype)  # (C, 3) optical axis in the world frame
    cos = (d * axis[:, None, None, :]).sum(-1)
    return o + d * (depth.to(d.dtype) / cos)[..., None]


def project_points(
    points: Tensor,  # (..., 3) world, metres
    viewmats: Tensor,  # (..., 4, 4) world-to-camera, broadcast against points' leading dimensions
    Ks: Tensor,  # (..., 3, 3) pixels
) -> tuple[Tensor, Tensor]:
    """Pinhole projection of world points, the inverse of :func:`unproject_pixels`: x_cam = R p + t, (u, v) =
    (f_x x/z + c_x, f_y y/z + c_y), pixel centres as in :func:`camera_rays`. Returns uv (..., 2) pixels and z (...)
    metres; (u, v) of points at z ≤ 0 are meaningless (mask with ``z > 0``).
    """
    cam = (viewmats[..., :3, :3] @ points[..., None])[..., 0] + viewmats[..., :3, 3]
    z = cam[..., 2]
    pix = (Ks @ cam[..., None])[..., 0]
    return pix[..., :2] / z[..., None], z


def unproject_pixels(
    uv: Tensor,  # (..., 2) pixels, centres at index + 0.5
    z: Tensor,  # (...) z-depth, metres
    viewmats: Tensor,  # (..., 4, 4) world-to-camera, broadcast against uv's leading dimensions
    Ks: Tensor,  # (..., 3, 3) pixels
) -> Tensor:
    """World points (..., 3), metres, at continuous pixel positions and z-depths: p = Rᵀ(z·K⁻¹(u, v, 1)ᵀ − t)."""
    pix = torch.cat([uv, torch.ones_like(uv[..., :1])], dim=-1)
    cam = (torch.linalg.inv(Ks) @ pix[..., None])[..., 0] * z[..., None]
    R, t = viewmats[..., :3, :3], viewmats[..., :3, 3]
    return (R.transpose(-1, -2) @ (cam - t)[..., None])[..., 0]


def plucker_rays(
    viewmats: Tensor,  # (C, 4, 4) world-to-camera
    Ks: Tensor,  # (C, 3, 3) pixels
    width: int,
    height: int,
) -> Tensor:
    """Plücker coordinates (C, H, W, 6) of every pixel's ray (CameraCtrl, He et al. 2024, Eq. 3): moment o × d
    (metres), then unit world direction d."""
    o, d = camera_rays(viewmats, Ks, width, height)
    return torch.cat([torch.linalg.cross(o, d, dim=-1), d], dim=-1)


def pack_plucker(
    rays: Tensor,  # (B, T, H, W, 6)
    temporal: int = 4,
    spatial: int = 8,
) -> Tensor:
    """Pack pixel-rate Plücker rays (B, T, H, W, 6), T = 1 + temporal·k, H and W multiples of ``spatial``, onto the
    VAE latent grid by space-/time-to-depth: frame 0 repeated ``temporal`` times, then groups of ``temporal`` frames
    (the VAE's causal grouping), each latent pixel gathering its ``spatial``² pixels.

    Returns:
        (B, 6·temporal·spatial², 1 + k, H/spatial, W/spatial), channels ordered (frame-in-group, row-in-block,
        column-in-block, ray component).

    Raises:
        ValueError: another shape.
    """
    if rays.dim() != 5 or rays.shape[-1] != 6:
        raise ValueError(f"rays must have shape (B, T, H, W, 6), got {tuple(rays.shape)}")
    B, T, H, W, _ = rays.shape
    if (T - 1) % temporal != 0:
        raise ValueError(f"frames must be 1 + {temporal}·k, got T = {T}")
    if H % spatial or W % spatial:
        raise ValueError(f"height and width must be multiples of {spatial}, got {H}×{W}")
    first = rays[:, :1].expand(B, temporal, H, W, 6)
    x = torch.cat([first, rays[:, 1:]], dim=1)  # (B, temporal·n, H, W, 6)
    n, h, w = x.shape[1] // temporal, H // spatial, W // spatial
    x = x.reshape(B, n, temporal, h, spatial, w, spatial, 6)
    x = x.permute(0, 2, 4, 6, 7, 1, 3, 5)  # (B, temporal, sy, sx, 6, n, h, w)
    return x.reshape(B, temporal * spatial * spatial * 6, n, h, w)
