"""Real spherical harmonics up to degree 3, INRIA 3DGS convention (view-dependent colour).

Basis and constants of the INRIA implementation (``sh_utils.py``, Kerbl et al. 2023 §5): the orthonormal real SH
of Sloan, "Stupid Spherical Harmonics (SH) Tricks" (2008), App. A2, Condon–Shortley phase, ordered l = 0..3,
m = −l..l. Colour = max(Σ_k c_k·Y_k(dir) + 0.5, 0) (docs/DESIGN.md "Colours").
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from diff4splat.cameras.path import camera_centers
from diff4splat.scene.gaussians import SH_C0

__all__ = ["SH_C0", "SH_C1", "SH_C2", "SH_C3", "num_sh_bases", "sh_basis", "spherical_harmonics", "sh_to_color",
           "color_features", "sh_rotation", "rotate_sh"]

SH_C1 = 0.4886025119029199  # sqrt(3/(4π))
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154, -0.4570457994644658,
         1.445305721320277, -0.5900435899266435)


def num_sh_bases(degree: int) -> int:
    """Number of coefficients (degree+1)² of an SH expansion up to ``degree``; ValueError unless 0 ≤ degree ≤ 3."""
    if isinstance(degree, bool) or not isinstance(degree, int) or not 0 <= degree <= 3:
        raise ValueError(f"sh_degree must be an int in 0..3, got {degree!r}")
    return (degree + 1) ** 2


def sh_basis(degree: int, dirs: Tensor) -> Tensor:
    """Real SH basis Y_k(dir), k < (degree+1)²: degree 0..3, dirs (..., 3) unit (not normalised here) →
    (..., (degree+1)²). ValueError: degree outside 0..3 or dirs without a trailing 3."""
    num_sh_bases(degree)
    if dirs.shape[-1] != 3:
        raise ValueError(f"dirs must have last dimension 3, got shape {tuple(dirs.shape)}")
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [SH_C2[0] * xy, SH_C2[1] * yz, SH_C2[2] * (2.0 * zz - xx - yy), SH_C2[3] * xz, SH_C2[4] * (xx - yy)]
    if degree >= 3:
        out += [
            SH_C3[0] * y * (3.0 * xx - yy),
            SH_C3[1] * xy * z,
            SH_C3[2] * y * (4.0 * zz - xx - yy),
            SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
            SH_C3[4] * x * (4.0 * zz - xx - yy),
            SH_C3[5] * z * (xx - yy),
            SH_C3[6] * x * (xx - 3.0 * yy),
        ]
    return torch.stack(out, dim=-1)


def spherical_harmonics(degrees_to_use: int, dirs: Tensor, coeffs: Tensor) -> Tensor:
    """(..., D) Σ_k coeffs_k·Y_k(dir), without the +0.5 offset (gsplat ``spherical_harmonics`` signature): the
    first (degree+1)² of coeffs (..., K, D) (broadcasting against dirs[..., None, :]) along dirs (..., 3), normalised
    here (zero: only the DC term survives). ValueError: degree outside 0..3 or too few coefficients."""
    k = num_sh_bases(degrees_to_use)
    if coeffs.dim() < 2 or coeffs.shape[-2] < k:
        raise ValueError(f"coeffs must have shape (..., K≥{k}, D) for degree {degrees_to_use}, "
                         f"got {tuple(coeffs.shape)}")
    basis = sh_basis(degrees_to_use, F.normalize(dirs, dim=-1))  # (..., k)
    return (basis[..., :, None] * coeffs[..., :k, :]).sum(-2)


def sh_to_color(sh_values: Tensor) -> Tensor:
    """INRIA colour from an SH value: max(value + 0.5, 0). (...) → (...)."""
    return torch.clamp_min(sh_values + 0.5, 0.0)


def color_features(
    colors: Tensor,  # (N, D) or (N, K, 3) SH
    means: Tensor,  # (N, 3)
    viewmats: Tensor,  # (C, 4, 4)
    sh_degree: int | None,
) -> Tensor:
    """Per-camera colours (C, N, D): ``colors`` as given, or with ``sh_degree`` max(SH(dir) + 0.5, 0) along
    dir = mean − camera centre (−Rᵀt), as gsplat ``rasterization``."""
    C, N = viewmats.shape[0], means.shape[0]
    if sh_degree is None:
        return colors[None].expand(C, N, colors.shape[-1])
    campos = camera_centers(viewmats)  # (C, 3)
    dirs = means[None] - campos[:, None]  # (C, N, 3)
    return sh_to_color(spherical_harmonics(sh_degree, dirs, colors[None]))


_ROTATION_SAMPLES = 64
"""Fibonacci-sphere directions :func:`sh_rotation` solves on (≥ 16, so the sampled basis has full column rank)."""


def sh_rotation(degree: int, R: Tensor) -> Tensor:
    """M (K, K), K = (degree+1)², with Y(Rᵀd) = M·Y(d) for every unit d (the block-diagonal real Wigner matrices).

    Solved by least squares on fixed directions (exact to float64 rounding: the relation is linear). degree 0..3,
    R (3, 3) rotation → (K, K) float64 on the CPU. ValueError: degree outside 0..3, or R not (3, 3).
    """
    k = num_sh_bases(degree)
    if tuple(R.shape) != (3, 3):
        raise ValueError(f"R must have shape (3, 3), got {tuple(R.shape)}")
    R = R.detach().to("cpu", torch.float64)
    i = torch.arange(_ROTATION_SAMPLES, dtype=torch.float64, device="cpu") + 0.5  # a (K, K) solve: on the host
    z = 1.0 - 2.0 * i / _ROTATION_SAMPLES
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i
    r = torch.sqrt(1.0 - z * z)
    dirs = torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], dim=-1)  # (S, 3) unit
    basis, rotated = sh_basis(degree, dirs), sh_basis(degree, dirs @ R)  # rows: Y(d)ᵀ and Y(Rᵀd)ᵀ
    return torch.linalg.lstsq(basis, rotated).solution.T[:k, :k]  # basis·Mᵀ = rotated


def rotate_sh(sh: Tensor, R: Tensor) -> Tensor:
    """SH coefficients of Gaussians rotated by R (world → world): c' = Mᵀc (:func:`sh_rotation`), so the new colour
    towards R·d is the old one towards d. sh (..., K, D), K in (1, 4, 9, 16) → (..., K, D) in ``sh``'s dtype and
    device. ValueError: K not a square ≤ 16, or R not (3, 3)."""
    k = sh.shape[-2] if sh.dim() >= 2 else 0
    degree = math.isqrt(k) - 1
    if k < 1 or (degree + 1) ** 2 != k or degree > 3:
        raise ValueError(f"sh must have shape (..., K, D) with K in (1, 4, 9, 16), got {tuple(sh.shape)}")
    if degree == 0:
        return sh
    m = sh_rotation(degree, R).to(sh.device, sh.dtype)
    return torch.einsum("kj,...kd->...jd", m, sh)  # c' = Mᵀc
