"""Camera conventions of the source datasets → ours (metres, OpenCV camera axes x right, y down, z forward,
world-to-camera ``viewmats``, pixel ``Ks`` with pixel centres at +0.5; FORMAT.md), each written once here. All pose
arithmetic is float64 numpy; :func:`camera_path` builds the validated :class:`~diff4splat.cameras.CameraPath`.
"""
from __future__ import annotations

import numpy as np
import torch

from diff4splat.cameras import CameraPath, invert_rigid
from diff4splat.scene.quaternions import ROTATION_TOL, quat_to_rotmat, rotation_errors

from ..format import timestamps_to_times

__all__ = ["INTEGER_CENTRE_SHIFT", "GL_TO_CV", "P3D_TO_CV", "NED_TO_CV", "rigid", "invert", "c2w_gl_to_viewmat",
           "c2w_cv_to_viewmat", "c2w_llff_to_gl", "quat_xyzw_to_rotmat", "normalize_rotation", "check_rotation",
           "intrinsics", "camera_path"]

INTEGER_CENTRE_SHIFT = 0.5
"""Pixels: our image coordinates (pixel centres at +0.5, FORMAT.md) minus those of conventions that put pixel centres
at integers (OpenCV, KITTI): a principal point given in the latter gets + this."""

GL_TO_CV = np.diag([1.0, -1.0, -1.0])
"""OpenGL/Blender camera axes (x right, y up, z back) ↔ OpenCV camera axes (its own inverse)."""
P3D_TO_CV = np.diag([-1.0, -1.0, 1.0])
"""PyTorch3D camera axes (x left, y up, z forward) ↔ OpenCV camera axes (its own inverse): R_cv = P·Rᵀ, t_cv = P·T
for its row-vector X_cam = X_world·R + T (PyTorch3D's ``opencv_from_cameras_projection``)."""
NED_TO_CV = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
"""Maps a vector in NED body axes (x forward, y right, z down; AirSim, TartanAir) to OpenCV camera axes."""


def rigid(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Stack rotations (..., 3, 3) and translations (..., 3) into (..., 4, 4) [R | t; 0 0 0 1] float64."""
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    out = np.zeros(R.shape[:-2] + (4, 4))
    out[..., :3, :3] = R
    out[..., :3, 3] = t
    out[..., 3, 3] = 1.0
    return out


def invert(mats: np.ndarray) -> np.ndarray:
    """Closed-form inverse of rigid transforms (..., 4, 4), via :func:`diff4splat.cameras.invert_rigid`."""
    return invert_rigid(torch.from_numpy(np.asarray(mats, dtype=np.float64))).numpy()


def c2w_cv_to_viewmat(c2w: np.ndarray) -> np.ndarray:
    """(..., 4, 4) camera-to-world with OpenCV camera axes → world-to-camera viewmats (float64)."""
    return invert(c2w)


def c2w_gl_to_viewmat(c2w: np.ndarray) -> np.ndarray:
    """(..., 4, 4) camera-to-world with OpenGL/Blender/NeRF camera axes (x right, y up, z back) → OpenCV
    world-to-camera: c2w_cv = c2w_gl · diag(1, −1, −1, 1) (NeRF code release), inverted."""
    c2w = np.array(c2w, dtype=np.float64)
    c2w[..., :3, :3] = c2w[..., :3, :3] @ GL_TO_CV
    return invert(c2w)


def c2w_llff_to_gl(c2w_llff: np.ndarray) -> np.ndarray:
    """(..., 3, 4) LLFF camera-to-world [down | right | backward | t] → (..., 4, 4) OpenGL camera-to-world, columns
    [c1, −c0, c2] as LLFF's ``load_llff.py`` and 4DGaussians' ``neural_3D_dataset_NDC.py`` (then
    :func:`c2w_gl_to_viewmat`)."""
    P = np.asarray(c2w_llff, dtype=np.float64)
    return rigid(np.stack([P[..., 1], -P[..., 0], P[..., 2]], axis=-1), P[..., 3])


def quat_xyzw_to_rotmat(q: np.ndarray) -> np.ndarray:
    """Quaternions (..., 4) stored x, y, z, w (Hamilton; ROS, TartanAir) → rotation matrices (..., 3, 3), normalised
    (:func:`diff4splat.scene.quaternions.quat_to_rotmat`). Raises ValueError: a zero-norm quaternion."""
    q = np.asarray(q, dtype=np.float64)
    wxyz = np.concatenate([q[..., 3:4], q[..., :3]], axis=-1)
    return quat_to_rotmat(torch.from_numpy(wxyz)).numpy()


def normalize_rotation(M: np.ndarray, name: str = "rotation") -> np.ndarray:
    """Remove a uniform scale from (..., 3, 3) scaled rotations s·R (MatrixCity's, s = 0.01): R = M / det(M)^(1/3).
    Raises ValueError naming ``name``: det(M) ≤ 0 or M / det^(1/3) not a rotation within
    :data:`~diff4splat.scene.quaternions.ROTATION_TOL` (a non-uniform scale or reflection is never projected away)."""
    M = np.asarray(M, dtype=np.float64)
    det = np.linalg.det(M)
    if (det <= 0).any():
        raise ValueError(f"{name} has a non-positive determinant (reflection or degenerate): {det.min():.3g}")
    R = M / np.cbrt(det)[..., None, None]
    check_rotation(R, name, "a uniformly scaled rotation")
    return R


def check_rotation(R: np.ndarray, name: str, what: str = "a rotation matrix") -> None:
    """Raise ValueError naming ``name`` unless every (..., 3, 3) matrix of ``R`` is orthonormal with det 1 within
    :data:`~diff4splat.scene.quaternions.ROTATION_TOL` (:func:`~diff4splat.scene.quaternions.rotation_errors`)."""
    ortho, det = (float(e.max()) for e in rotation_errors(torch.from_numpy(np.asarray(R, dtype=np.float64))))
    if max(ortho, det) > ROTATION_TOL:
        raise ValueError(f"{name} must be {what} (max |RᵀR − I| = {ortho:.3g}, |det R − 1| = {det:.3g})")


def intrinsics(fx, fy, cx, cy) -> np.ndarray:
    """(T, 3, 3) float64 pixel intrinsics from per-frame (T,) or scalar fx, fy, cx, cy (broadcast)."""
    fx, fy, cx, cy = np.broadcast_arrays(*(np.atleast_1d(np.asarray(v, dtype=np.float64)) for v in (fx, fy, cx, cy)))
    K = np.zeros(fx.shape + (3, 3))
    K[..., 0, 0], K[..., 1, 1], K[..., 0, 2], K[..., 1, 2], K[..., 2, 2] = fx, fy, cx, cy, 1.0
    return K


def camera_path(viewmats: np.ndarray, Ks: np.ndarray, width: int, height: int,
                timestamps: np.ndarray) -> CameraPath:
    """A validated float64 :class:`CameraPath` of (T, 4, 4) OpenCV world-to-camera ``viewmats`` (metres), (T, 3, 3) or
    (3, 3) pixel ``Ks``, the image size and times = normalised (T,) ``timestamps`` in seconds (FORMAT.md). Raises
    ValueError from :meth:`CameraPath.validate` (e.g. an improper rotation after conversion)."""
    V = torch.from_numpy(np.ascontiguousarray(viewmats, dtype=np.float64))
    K = np.asarray(Ks, dtype=np.float64)
    if K.ndim == 2:
        K = np.broadcast_to(K, (V.shape[0], 3, 3))
    times = torch.from_numpy(timestamps_to_times(timestamps))
    return CameraPath(V, torch.from_numpy(np.ascontiguousarray(K)), int(width), int(height), times)
