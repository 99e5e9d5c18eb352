"""Quaternion algebra (wxyz, Hamilton product) shared by the scene, renderer and networks.

Conventions (docs/DESIGN.md): quaternions are stored unnormalised and normalised on use; a
zero-norm quaternion is an error, never a silent NaN.
"""
from __future__ import annotations

import torch
from torch import Tensor

__all__ = [
    "quat_normalize",
    "quat_norms",
    "quat_multiply",
    "quat_conjugate",
    "quat_to_rotmat",
    "rotmat_to_quat",
    "quat_nlerp",
    "axis_angle_to_quat",
    "rotation_errors",
    "ROTATION_TOL",
]

_ZERO_NORM = 1e-12
"""A quaternion with a smaller norm has no orientation (:func:`quat_normalize` refuses it)."""
ROTATION_TOL = 1e-4
"""Largest :func:`rotation_errors` of a matrix taken as a rotation (camera paths, scene files, converters): a float32
rotation passes by orders of magnitude, a 1 % scale or shear does not."""


def rotation_errors(R: Tensor) -> tuple[Tensor, Tensor]:
    """How far matrices are from rotations: max |RᵀR − I| entry and |det R − 1|, computed in float64.

    The one test of rotation matrices (camera paths, the renderer's viewmats, dataset converters); a reflection has
    RᵀR = I and det −1.

    Args:
        R: (..., 3, 3).

    Returns:
        orthonormality error (...), determinant error (...), float64, on R's device.
    """
    R = R.detach().double()
    eye = torch.eye(3, dtype=R.dtype, device=R.device)
    ortho = (R.transpose(-1, -2) @ R - eye).abs().amax(dim=(-2, -1))
    return ortho, (torch.linalg.det(R) - 1.0).abs()


def quat_normalize(quats: Tensor, name: str = "quats") -> Tensor:
    """Normalise quaternions to unit norm.

    Args:
        quats: (..., 4) wxyz, any non-zero norm.
        name: tensor name used in the error message.

    Returns:
        (..., 4) unit quaternions.

    Raises:
        ValueError: if any quaternion has norm below 1e-12 (orientation undefined).
    """
    return quats / quat_norms(quats, name)[..., None]


def quat_norms(quats: Tensor, name: str = "quats") -> Tensor:
    """The norms of quaternions, checked: (..., 4) wxyz → (...,), each ≥ 1e-12.

    The check of :func:`quat_normalize` without its (..., 4) result: a validation of a large deformation
    (K × N quaternions) holds one value per quaternion instead of a normalised copy.

    Raises:
        ValueError: last dimension not 4, or a quaternion with norm below 1e-12 (orientation undefined).
    """
    if quats.shape[-1] != 4:
        raise ValueError(f"{name} must have last dimension 4 (wxyz), got shape {tuple(quats.shape)}")
    norm = torch.linalg.vector_norm(quats, dim=-1)
    if quats.numel() and bool((norm < _ZERO_NORM).any()):
        idx = int((norm.reshape(-1) < _ZERO_NORM).nonzero()[0])
        raise ValueError(f"{name} has a zero-norm quaternion at flat index {idx}")
    return norm


def quat_multiply(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product a ⊗ b of wxyz quaternions (broadcasting).

    Args:
        a: (..., 4) wxyz.
        b: (..., 4) wxyz.

    Returns:
        (..., 4) wxyz; R(a ⊗ b) = R(a) R(b) for unit quaternions.
    """
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        dim=-1,
    )


def quat_conjugate(q: Tensor) -> Tensor:
    """Conjugate (w, −x, −y, −z); the inverse of a unit quaternion. q: (..., 4) → (..., 4)."""
    return q * q.new_tensor([1.0, -1.0, -1.0, -1.0])


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """Rotation matrices of (not necessarily unit) wxyz quaternions.

    Args:
        quats: (..., 4) wxyz, non-zero norm; normalised here.

    Returns:
        (..., 3, 3) rotation matrices (active rotation, column vectors: x' = R x).

    Raises:
        ValueError: zero-norm quaternion.
    """
    w, x, y, z = quat_normalize(quats).unbind(-1)
    r = torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    )
    return r.reshape(quats.shape[:-1] + (3, 3))


def rotmat_to_quat(rotmats: Tensor) -> Tensor:
    """Unit wxyz quaternions (w ≥ 0) of rotation matrices (Shepperd's method, branch-free).

    Args:
        rotmats: (..., 3, 3) proper rotations.

    Returns:
        (..., 4) unit wxyz quaternions with non-negative w.
    """
    m = rotmats
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    m01, m02, m10, m12, m20, m21 = m[..., 0, 1], m[..., 0, 2], m[..., 1, 0], m[..., 1, 2], m[..., 2, 0], m[..., 2, 1]
    # Four candidate solutions; pick the numerically best (largest |component|) per matrix.
    cands = torch.stack(
        [
            torch.stack([1 + m00 + m11 + m22, m21 - m12, m02 - m20, m10 - m01], -1),
            torch.stack([m21 - m12, 1 + m00 - m11 - m22, m01 + m10, m02 + m20], -1),
            torch.stack([m02 - m20, m01 + m10, 1 - m00 + m11 - m22, m12 + m21], -1),
            torch.stack([m10 - m01, m02 + m20, m12 + m21, 1 - m00 - m11 + m22], -1),
        ],
        dim=-2,
    )  # (..., 4, 4): row k is 4·q_k·q
    diag = torch.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    best = diag.argmax(-1, keepdim=True)
    q = torch.gather(cands, -2, best[..., None].expand(best.shape[:-1] + (1, 4))).squeeze(-2)
    q = q / q.norm(dim=-1, keepdim=True)
    return torch.where(q[..., :1] < 0, -q, q)


def quat_nlerp(q0: Tensor, q1: Tensor, w: Tensor | float) -> Tensor:
    """Normalised linear interpolation between the rotations of two quaternions, taking the shorter arc.

    The inputs are normalised first: q and c·q (c > 0) are the same rotation, and a blend of unnormalised inputs
    would weigh each by its norm (the viewer page, which receives unit keyframes, interpolates as this does).

    Args:
        q0: (..., 4) wxyz, any non-zero norm.
        q1: (..., 4) wxyz, any non-zero norm.
        w: weight in [0, 1] (scalar or broadcastable (..., 1)); 0 → q0/|q0|, 1 → q1/|q1|.

    Returns:
        (..., 4) unit quaternion normalize((1−w)·u0 + w·sign(u0·u1)·u1), u = q/|q| (norm of the blend ≥ 1/√2).

    Raises:
        ValueError: a zero-norm input.
    """
    q0, q1 = quat_normalize(q0, "q0"), quat_normalize(q1, "q1")
    sign = torch.where((q0 * q1).sum(-1, keepdim=True) < 0, -1.0, 1.0).to(q1.dtype)
    return quat_normalize((1 - w) * q0 + w * sign * q1, "interpolated quaternion")


def axis_angle_to_quat(axis: Tensor, angle: Tensor) -> Tensor:
    """Unit wxyz quaternion of a rotation by ``angle`` (radians) about ``axis``.

    Args:
        axis: (..., 3), non-zero; normalised here.
        angle: (...) radians.

    Returns:
        (..., 4) (cos(θ/2), sin(θ/2)·axis).
    """
    axis = axis / axis.norm(dim=-1, keepdim=True)
    half = angle[..., None] / 2
    return torch.cat([torch.cos(half), torch.sin(half) * axis], dim=-1)
