"""EWA projection of 3D Gaussians to screen space (pinhole): the pure-PyTorch reference of every path's projection.

3DGS (Kerbl et al. 2023, §4) with EWA splatting (Zwicker et al. 2002, eq. 31), matching gsplat's
``fully_fused_projection`` (clamped Jacobian, eps2d blur, 3σ radius, culling). Also :func:`splat_alpha`, the one
definition of a Gaussian's opacity at a pixel, shared by every compositor.
"""
from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from diff4splat.render.settings import CAMERA_MODEL, EPS2D, FAR_PLANE, NEAR_PLANE
from diff4splat.scene.quaternions import quat_to_rotmat
from diff4splat.utils.constants import ALPHA_MAX, ALPHA_MIN, OPACITY_LOG_FLOOR

__all__ = ["RADIUS_MAX", "FOV_MARGIN", "EIGEN_FLOOR", "Projection", "covariance_3d", "persp_jacobian",
           "project_gaussians", "support_extent", "splat_sigma", "splat_alpha", "matmul"]

RADIUS_MAX = 1 << 30
"""Screen radii are clamped to this (pixels) before the int32 cast (exact in float32)."""
FOV_MARGIN = 0.3
"""The Jacobian's x/z (y/z) is clamped to the field of view widened by this fraction of tan½fov per side (gsplat)."""
EIGEN_FLOOR = 0.01
"""Floor of b² − det under the square root of the larger eigenvalue of Σ2d, pixels⁴ (gsplat's 3σ radius)."""


class _MatmulFullPrecision(torch.autograd.Function):
    """``a @ b`` (broadcasting) with autocast off in forward and backward (autocast also lowers the backward)."""

    @staticmethod
    def forward(ctx, a, b):  # noqa: D102
        ctx.save_for_backward(a, b)
        ctx.device_type = a.device.type
        with torch.autocast(ctx.device_type, enabled=False):
            return a @ b

    @staticmethod
    def backward(ctx, g):  # noqa: D102
        a, b = ctx.saved_tensors
        with torch.autocast(ctx.device_type, enabled=False):
            ga = (g @ b.transpose(-1, -2)).sum_to_size(a.shape) if ctx.needs_input_grad[0] else None
            gb = (a.transpose(-1, -2) @ g).sum_to_size(b.shape) if ctx.needs_input_grad[1] else None
        return ga, gb


def matmul(a: Tensor, b: Tensor) -> Tensor:
    """``a @ b`` in the inputs' dtype even under ``torch.autocast``, forward and backward.
    (..., n, k), (..., k, m) → (..., n, m)."""
    return _MatmulFullPrecision.apply(a, b)


class Projection(NamedTuple):
    """Screen-space Gaussians for C cameras, indexed (camera, Gaussian).

    Attributes:
        means2d: (C, N, 2) projected centres, pixels (x right, y down).
        depths: (C, N) camera-space z of the centres, metres.
        covars2d: (C, N, 3) dilated screen covariance (Σxx, Σxy, Σyy) = Σ2d + eps2d·I, pixels².
        conics: (C, N, 3) its inverse (a, b, c): σ(d) = ½(a dx² + c dy²) + b dx dy, 1/pixels².
        opacities: (C, N) opacities used for compositing (× compensation when antialiased).
        radii: (C, N) int32 3σ screen radius ceil(3·sqrt(λmax)), pixels, clamped to :data:`RADIUS_MAX`;
            0 marks a culled Gaussian.
        compensations: (C, N) sqrt(det Σ2d / det(Σ2d + eps2d·I)), or None in classic mode.
    """

    means2d: Tensor
    depths: Tensor
    covars2d: Tensor
    conics: Tensor
    opacities: Tensor
    radii: Tensor
    compensations: Tensor | None


def covariance_3d(quats: Tensor, scales: Tensor) -> Tensor:
    """World covariance Σ = R S Sᵀ Rᵀ (3DGS eq. 6), (N, 3, 3) metres², from quats (N, 4) wxyz (unnormalised) and
    scales (N, 3) metres. ValueError: a zero-norm quaternion (:func:`diff4splat.scene.quaternions.quat_to_rotmat`)."""
    m = quat_to_rotmat(quats) * scales[..., None, :]  # R S
    return matmul(m, m.transpose(-1, -2))


def persp_jacobian(
    means_c: Tensor,  # (C, N, 3) camera frame, z ≠ 0
    Ks: Tensor,  # (C, 3, 3)
    width: int,
    height: int,
) -> tuple[Tensor, Tensor]:
    """Pinhole projection of camera-frame centres and its clamped perspective Jacobian (EWA splatting eq. 29–31).

    mean2d = (fx·x/z + cx, fy·y/z + cy); J = [[fx/z, 0, −fx·tx/z²], [0, fy/z, −fy·ty/z²]] where, as gsplat's
    ``persp_proj``, tx/z is clamped to [−(cx/fx + m·tan½fovx), (W−cx)/fx + m·tan½fovx], m = :data:`FOV_MARGIN`,
    tan½fovx = W/(2fx); same for y. Σ2d = J Σc Jᵀ.

    Returns:
        means2d: (C, N, 2) pixels;  J: (C, N, 2, 3) pixels per metre.
    """
    x, y, z = means_c.unbind(-1)
    fx, fy = Ks[:, 0, 0, None], Ks[:, 1, 1, None]
    cx, cy = Ks[:, 0, 2, None], Ks[:, 1, 2, None]
    tan_fovx = 0.5 * width / fx
    tan_fovy = 0.5 * height / fy
    rz = 1.0 / z
    lim_x, lim_y = FOV_MARGIN * tan_fovx, FOV_MARGIN * tan_fovy
    tx = z * torch.clamp(x * rz, min=-(cx / fx + lim_x), max=(width - cx) / fx + lim_x)
    ty = z * torch.clamp(y * rz, min=-(cy / fy + lim_y), max=(height - cy) / fy + lim_y)
    zeros = torch.zeros_like(z)
    J = torch.stack(
        [fx * rz, zeros, -fx * tx * rz * rz, zeros, fy * rz, -fy * ty * rz * rz], dim=-1
    ).reshape(z.shape + (2, 3))
    return torch.stack([fx * x * rz + cx, fy * y * rz + cy], dim=-1), J


def project_gaussians(
    means: Tensor,  # (N, 3)
    quats: Tensor,  # (N, 4)
    scales: Tensor,  # (N, 3)
    opacities: Tensor,  # (N,)
    viewmats: Tensor,  # (C, 4, 4)
    Ks: Tensor,  # (C, 3, 3)
    width: int,
    height: int,
    *,
    near_plane: float = NEAR_PLANE,
    far_plane: float = FAR_PLANE,
    eps2d: float = EPS2D,
    antialiased: bool = False,
    camera_model: str = CAMERA_MODEL,
) -> Projection:
    """Project Gaussians into C cameras and cull them, as gsplat's ``fully_fused_projection``.

    Steps (gsplat CUDA kernel order): camera-frame centre; cull z < near_plane, z ≤ 0 or z > far_plane;
    Σ2d = J Σc Jᵀ (:func:`persp_jacobian`), its determinant as the sum of the squared 2×2 minors of J·R_cam·R·S
    (Cauchy–Binet: no cancellation for elongated Gaussians in float32); dilation Σ2d + eps2d·I with compensation
    sqrt(max(0, det Σ2d / det(Σ2d + eps2d·I))) (Mip-Splatting eq. 9, used when ``antialiased``);
    cull det ≤ 0; conic = (Σ2d + eps2d·I)⁻¹; radius = ceil(3·sqrt(b + sqrt(max(:data:`EIGEN_FLOOR`, b² − det))))
    with b = ½ trace; cull radius ≤ 0 and Gaussians whose radius box lies fully outside the image.
    Culled Gaussians get radius 0, zeros elsewhere and exactly zero gradient (computed from a safe depth).

    Args: as :func:`diff4splat.render.rasterize` (metres, pixels; viewmats OpenCV world-to-camera);
    ``antialiased`` multiplies opacities by the compensation; ``camera_model`` must be "pinhole".

    Raises:
        ValueError: a camera model other than "pinhole", or a zero-norm quaternion.
    """
    if camera_model != "pinhole":
        raise ValueError(f"camera_model must be 'pinhole' here (the ray path, raytrace, renders the others), "
                         f"got {camera_model!r}")
    R = viewmats[:, :3, :3]
    means_c = matmul(means[None], R.transpose(-1, -2)) + viewmats[:, None, :3, 3]
    z = means_c[..., 2]
    in_depth = (z >= near_plane) & (z > 0) & (z <= far_plane)  # z > 0: near_plane = 0 may not divide by z = 0
    safe_means_c = torch.where(in_depth[..., None], means_c, means_c.new_tensor([0.0, 0.0, 1.0]))
    means2d, J = persp_jacobian(safe_means_c, Ks, width, height)
    # Σ2d = A Aᵀ with A = J·R_cam·R·S (C, N, 2, 3), whose columns are the projected axes s_k·(J R_cam R e_k): det Σ2d
    # is the sum of A's squared 2×2 minors (Cauchy–Binet), products of the axes' own lengths, where sxx·syy − sxy²
    # cancels the long axis's L⁴ (in float32 it would cull a 1 km × 1 cm Gaussian)
    A = matmul(J, matmul(R[:, None], (quat_to_rotmat(quats) * scales[..., None, :])[None]))
    cov = matmul(A, A.transpose(-1, -2))
    sxx, sxy, syy = cov[..., 0, 0], cov[..., 0, 1], cov[..., 1, 1]
    det_orig = torch.linalg.cross(A[..., 0, :], A[..., 1, :]).square().sum(-1)
    det = det_orig + eps2d * (sxx + syy) + eps2d * eps2d  # det(Σ2d + ε·I)
    sxx, syy = sxx + eps2d, syy + eps2d
    valid = in_depth & (det > 0)
    safe_det = torch.where(valid, det, torch.ones_like(det))
    conics = torch.stack([syy / safe_det, -sxy / safe_det, sxx / safe_det], dim=-1)
    compensations = None
    if antialiased:  # sqrt'(0) is infinite: a line or point Gaussian (det Σ2d = 0) gets 0 and a zero gradient
        ratio = det_orig / safe_det
        positive = ratio > 0
        compensations = torch.where(positive, torch.sqrt(torch.where(positive, ratio, torch.ones_like(ratio))),
                                    torch.zeros_like(ratio))
    with torch.no_grad():
        b = 0.5 * (sxx + syy)
        v1 = b + torch.sqrt(torch.clamp(b * b - det, min=EIGEN_FLOOR))
        radius = torch.ceil(3.0 * torch.sqrt(torch.clamp(v1, min=0.0)))
        mx, my = means2d[..., 0], means2d[..., 1]
        inside = (mx + radius > 0) & (mx - radius < width) & (my + radius > 0) & (my - radius < height)
        keep = valid & (radius > 0) & inside
        radii = torch.where(keep, radius.clamp(max=float(RADIUS_MAX)), torch.zeros_like(radius)).to(torch.int32)
    op = opacities[None, :].expand_as(z)
    if compensations is not None:
        op = op * compensations
    k = keep[..., None]
    return Projection(
        means2d=torch.where(k, means2d, 0.0),
        depths=torch.where(keep, z, 0.0),
        covars2d=torch.where(k, torch.stack([sxx, sxy, syy], dim=-1), 0.0),
        conics=torch.where(k, conics, 0.0),
        opacities=torch.where(keep, op, 0.0),
        radii=radii,
        compensations=None if compensations is None else torch.where(keep, compensations, 0.0),
    )


def support_extent(covars2d: Tensor, opacities: Tensor) -> Tensor:
    """Half-size of the screen box outside which a Gaussian's alpha is below :data:`ALPHA_MIN`.

    alpha = min(0.99, o·exp(−σ)) ≥ 1/255 ⇔ σ ≤ τ = ln(255·o); on the ellipse ½dᵀΣ⁻¹d = τ the largest |dx| is
    sqrt(2τ·Σxx) (y: Σyy), gsplat's opacity-aware box (Radl et al. 2024, StopThePop, App. B.2), plus a
    0.1 % + 1e-3 px margin for rounding. covars2d (..., 3) (Σxx, Σxy, Σyy) pixels², opacities (...) →
    (..., 2) half extents (x, y), pixels; negative where never visible (o < 1/255).
    """
    tau = torch.log(torch.clamp(opacities, min=OPACITY_LOG_FLOOR) / ALPHA_MIN)
    var = torch.stack([covars2d[..., 0], covars2d[..., 2]], dim=-1).clamp(min=0.0)
    ext = torch.sqrt(2.0 * tau.clamp(min=0.0)[..., None] * var) * 1.001 + 1e-3
    return torch.where((tau >= 0)[..., None], ext, torch.full_like(ext, -1.0))


def splat_sigma(dx: Tensor, dy: Tensor, conics: Tensor) -> Tensor:
    """Gaussian exponent σ = ½(a·dx² + c·dy²) + b·dx·dy (3DGS eq. 2, conic form), dimensionless.

    dx, dy: (...) pixel centre minus projected centre, pixels; conics (..., 3) (a, b, c), 1/pixels², broadcasting.
    """
    a, b, c = conics.unbind(-1)
    return 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy


def splat_alpha(dx: Tensor, dy: Tensor, conics: Tensor, opacities: Tensor) -> Tensor:
    """Opacity at pixel offsets with the 3DGS skip rule: alpha = min(0.99, o·exp(−σ)) (σ: :func:`splat_sigma`),
    0 where σ < 0 or alpha < 1/255 (gsplat ``rasterize_to_pixels``). Arguments as :func:`splat_sigma`, opacities
    (...) in [0, 1], all broadcasting → (...) alpha in {0} ∪ [1/255, 0.99]."""
    sigma = splat_sigma(dx, dy, conics)
    alpha = torch.clamp(opacities * torch.exp(-sigma), max=ALPHA_MAX)
    keep = (sigma >= 0) & (alpha >= ALPHA_MIN)
    return torch.where(keep, alpha, torch.zeros_like(alpha))
