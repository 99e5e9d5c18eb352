"""Quaternion algebra (wxyz, Hamilton product) shared by the scene, renderer and networks.

Conventions (docs/DESIGN.md): quaternions are stored unnormalised and normalised on use; a
zero-norm quaternion is an error, never a silent NaN.
"""
from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["quat_normalize", "quat_norms", "quat_multiply", "quat_conjugate", "quat_to_rotmat", "rotmat_to_quat",
           "quat_nlerp", "axis_angle_to_quat", "rotation_errors", "ROTATION_TOL"]

_ZERO_NORM = 1e-12
"""A quaternion with a smaller norm has no orientation (:func:`quat_normalize` refuses it)."""
ROTATION_TOL = 1e-4
"""Largest :func:`rotation_errors` of a matrix taken as a rotation: float32 rotations pass, a 1 % scale or shear does
not."""


def rotation_errors(R: Tensor) -> tuple[Tensor, Tensor]:
    """How far (..., 3, 3) matrices are from rotations: (max |RᵀR − I| entry, |det R − 1|), each (...) float64 on R's
    device (a reflection has det −1)."""
    R = R.detach().double()
    eye = torch.eye(3, dtype=R.dtype, device=R.device)
    ortho = (R.transpose(-1, -2) @ R - eye).abs().amax(dim=(-2, -1))
    return ortho, (torch.linalg.det(R) - 1.0).abs()


def quat_normalize(quats: Tensor, name: str = "quats") -> Tensor:
    """(..., 4) wxyz quaternions normalised to unit norm; ``name`` is used in the error message.

    Raises:
        ValueError: a quaternion with norm below 1e-12 (orientation undefined).
    """
    return quats / quat_norms(quats, name)[..., None]


def quat_norms(quats: Tensor, name: str = "quats") -> Tensor:
    """The checked norms (...,) of (..., 4) wxyz quaternions: :func:`quat_normalize`'s check without a normalised copy.

    Raises:
        ValueError: last dimension not 4, or a quaternion with norm below 1e-12.
    """
    if quats.shape[-1] != 4:
        raise ValueError(f"{name} must have last dimension 4 (wxyz), got shape {tuple(quats.shape)}")
    norm = torch.linalg.vector_norm(quats, dim=-1)
    if quats.numel() and bool((norm < _ZERO_NORM).any()):
        idx = int((norm.reshape(-1) < _ZERO_NORM).nonzero()[0])
        raise ValueError(f"{name} has a zero-norm quaternion at flat index {idx}")
    return norm


def quat_multiply(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product a ⊗ b of (..., 4) wxyz quaternions (broadcasting); R(a ⊗ b) = R(a) R(b) for unit quaternions."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([aw * bw - ax * bx - ay * by - az * bz,
                        aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx,
                        aw * bz + ax * by - ay * bx + az * bw], dim=-1)


def quat_conjugate(q: Tensor) -> Tensor:
    """Conjugate (w, −x, −y, −z); the inverse of a unit quaternion. q: (..., 4) → (..., 4)."""
    return q * q.new_tensor([1.0, -1.0, -1.0, -1.0])


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """(..., 3, 3) rotation matrices (x' = R x) of (..., 4) wxyz quaternions of non-zero norm (normalised here).

    Raises:
        ValueError: a zero-norm quaternion.
    """
    w, x, y, z = quat_normalize(quats).unbind(-1)
    r = torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                     2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                     2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], dim=-1)
    return r.reshape(quats.shape[:-1] + (3, 3))


def rotmat_to_quat(rotmats: Tensor) -> Tensor:
    """(..., 4) unit wxyz quaternions, w ≥ 0, of (..., 3, 3) proper rotations (Shepperd's method, branch-free)."""
    m = rotmats
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    m01, m02, m10, m12, m20, m21 = m[..., 0, 1], m[..., 0, 2], m[..., 1, 0], m[..., 1, 2], m[..., 2, 0], m[..., 2, 1]
    # Four candidate solutions; pick the numerically best (largest |component|) per matrix.
    cands = torch.stack([torch.stack([1 + m00 + m11 + m22, m21 - m12, m02 - m20, m10 - m01], -1),
                         torch.stack([m21 - m12, 1 + m00 - m11 - m22, m01 + m10, m02 + m20], -1),
                         torch.stack([m02 - m20, m01 + m10, 1 - m00 + m11 - m22, m12 + m21], -1),
                         torch.stack([m10 - m01, m02 + m20, m12 + m21, 1 - m00 - m11 + m22], -1)],
                        dim=-2)  # (..., 4, 4): row k is 4·q_k·q
    diag = torch.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    best = diag.argmax(-1, keepdim=True)
    q = torch.gather(cands, -2, best[..., None].expand(best.shape[:-1] + (1, 4))).squeeze(-2)
    q = q / q.norm(dim=-1, keepdim=True)
    return torch.where(q[..., :1] < 0, -q, q)


def quat_nlerp(q0: Tensor, q1: Tensor, w: Tensor | float) -> Tensor:
    """Normalised linear interpolation between (..., 4) quaternions of any non-zero norm, shorter arc:
    normalize((1−w)·u0 + w·sign(u0·u1)·u1), u = q/|q|, w in [0, 1] (scalar or broadcastable (..., 1)).

    Raises:
        ValueError: a zero-norm input.
    """
    q0, q1 = quat_normalize(q0, "q0"), quat_normalize(q1, "q1")
    sign = torch.where((q0 * q1).sum(-1, keepdim=True) < 0, -1.0, 1.0).to(q1.dtype)
    return quat_normalize((1 - w) * q0 + w * sign * q1, "interpolated quaternion")


def axis_angle_to_quat(axis: Tensor, angle: Tensor) -> Tensor:
    """(..., 4) unit wxyz quaternion (cos(θ/2), sin(θ/2)·axis) of a rotation by ``angle`` (...) radians about ``axis``
    (..., 3), non-zero (normalised here)."""
    axis = axis / axis.norm(dim=-1, keepdim=True)
    half = angle[..., None] / 2
    return torch.cat([torch.cos(half), torch.sin(half) * axis], dim=-1)
