"""Camera conventions of the source datasets → ours, shared by every converter.

Every converter turns a source dataset's native conventions into the scene format's
(``data_prep/FORMAT.md``, docs/DESIGN.md): metres, OpenCV camera axes (x right, y down, z forward),
world-to-camera ``viewmats``, pixel ``Ks``, +inf for invalid depth. The axis changes needed by the
sources are collected here so that each is written once:

- OpenGL / Blender / NeRF camera axes (x right, y up, z backward) → OpenCV: flip the camera's y and
  z axes, c2w_cv = c2w_gl · diag(1, −1, −1, 1) (Mildenhall et al., NeRF code release; MatrixCity
  README "same pose coordinate system as NeRF").
- PyTorch3D camera axes (x left, y up, z forward, row-vector convention X_cam = X_world·R + T)
  → OpenCV: R_cv = diag(−1, −1, 1)·Rᵀ, t_cv = diag(−1, −1, 1)·T (the transform of PyTorch3D's
  ``opencv_from_cameras_projection``).
- NED body axes (x forward, y right, z down; AirSim / TartanAir) → OpenCV: x_cv = y_ned,
  y_cv = z_ned, z_cv = x_ned.
- LLFF camera-to-world columns (down, right, backward; ``poses_bounds.npy``) → OpenGL (right, up,
  backward) by the column permutation [1, −0, 2] of LLFF's ``load_llff.py`` and 4DGaussians'
  ``neural_3D_dataset_NDC.py``, then → OpenCV as above.

All pose arithmetic is float64 numpy; :func:`camera_path` builds the float64
:class:`~diff4splat.cameras.CameraPath` (validated: proper rotations, positive focal lengths).
"""
from __future__ import annotations

import numpy as np
import torch

from diff4splat.cameras import CameraPath, invert_rigid
from diff4splat.scene.quaternions import ROTATION_TOL, quat_to_rotmat, rotation_errors

from ..format import timestamps_to_times

__all__ = [
    "INTEGER_CENTRE_SHIFT",
    "GL_TO_CV",
    "P3D_TO_CV",
    "NED_TO_CV",
    "rigid",
    "invert",
    "c2w_gl_to_viewmat",
    "c2w_cv_to_viewmat",
    "c2w_llff_to_gl",
    "quat_xyzw_to_rotmat",
    "normalize_rotation",
    "check_rotation",
    "intrinsics",
    "camera_path",
]

INTEGER_CENTRE_SHIFT = 0.5
"""Pixels: our image coordinates (pixel centres at +0.5, FORMAT.md) minus those of conventions that put pixel centres
at integers (OpenCV, KITTI): a principal point given in the latter gets + this."""

GL_TO_CV = np.diag([1.0, -1.0, -1.0])
"""OpenGL/Blender camera axes (x right, y up, z back) ↔ OpenCV camera axes (its own inverse)."""

P3D_TO_CV = np.diag([-1.0, -1.0, 1.0])
"""PyTorch3D camera axes (x left, y up, z forward) ↔ OpenCV camera axes (its own inverse)."""

NED_TO_CV = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
"""Maps a vector in NED body axes (x forward, y right, z down) to OpenCV camera axes."""


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
    """(..., 4, 4) camera-to-world with OpenGL/Blender camera axes → OpenCV world-to-camera viewmats.

    c2w_cv = c2w_gl · diag(1, −1, −1, 1) (module docstring), then inverted.
    """
    c2w = np.array(c2w, dtype=np.float64)
    c2w[..., :3, :3] = c2w[..., :3, :3] @ GL_TO_CV
    return invert(c2w)


def c2w_llff_to_gl(c2w_llff: np.ndarray) -> np.ndarray:
    """(..., 3, 4) LLFF camera-to-world [down | right | backward | t] → (..., 4, 4) OpenGL camera-to-world.

    Columns reordered to [right, up, backward] = [c1, −c0, c2] (module docstring); feed the result to
    :func:`c2w_gl_to_viewmat`.
    """
    P = np.asarray(c2w_llff, dtype=np.float64)
    return rigid(np.stack([P[..., 1], -P[..., 0], P[..., 2]], axis=-1), P[..., 3])


def quat_xyzw_to_rotmat(q: np.ndarray) -> np.ndarray:
    """Quaternions (..., 4) stored x, y, z, w (Hamilton, as in ROS/TartanAir) → rotation matrices (..., 3, 3).

    Reorders to wxyz and calls :func:`diff4splat.scene.quaternions.quat_to_rotmat` (normalised on use).

    Raises:
        ValueError: a zero-norm quaternion.
    """
    q = np.asarray(q, dtype=np.float64)
    wxyz = np.concatenate([q[..., 3:4], q[..., :3]], axis=-1)
    return quat_to_rotmat(torch.from_numpy(wxyz)).numpy()


def normalize_rotation(M: np.ndarray, name: str = "rotation") -> np.ndarray:
    """Remove a uniform scale from (..., 3, 3) scaled rotations: R = M / det(M)^(1/3).

    Some exporters store s·R (MatrixCity's ``transform_matrix``, s = 0.01). A non-uniform scale or
    a reflection is an error, not something to be silently projected away.

    Raises:
        ValueError: naming ``name``, if det(M) ≤ 0 or M / det^(1/3) is not a rotation within
            :data:`~diff4splat.scene.quaternions.ROTATION_TOL` (:func:`~diff4splat.scene.quaternions.rotation_errors`).
    """
    M = np.asarray(M, dtype=np.float64)
    det = np.linalg.det(M)
    if (det <= 0).any():
        raise ValueError(f"{name} has a non-positive determinant (reflection or degenerate): {det.min():.3g}")
    R = M / np.cbrt(det)[..., None, None]
    check_rotation(R, name, "a uniformly scaled rotation")
    return R


def check_rotation(R: np.ndarray, name: str, what: str = "a rotation matrix") -> None:
    """Raise ValueError naming ``name`` unless every (..., 3, 3) matrix of ``R`` is a rotation within
    :data:`~diff4splat.scene.quaternions.ROTATION_TOL` (:func:`~diff4splat.scene.quaternions.rotation_errors`:
    orthonormal, det 1).
    """
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
    """A validated float64 :class:`CameraPath` with times = normalised ``timestamps`` (FORMAT.md).

    Args:
        viewmats: (T, 4, 4) world-to-camera, OpenCV axes, metres.
        Ks: (T, 3, 3) or (3, 3) pixel intrinsics.
        width, height: image size in pixels.
        timestamps: (T,) seconds, non-decreasing.

    Raises:
        ValueError: from :meth:`CameraPath.validate` (e.g. an improper rotation after conversion).
    """
    V = torch.from_numpy(np.ascontiguousarray(viewmats, dtype=np.float64))
    K = np.asarray(Ks, dtype=np.float64)
    if K.ndim == 2:
        K = np.broadcast_to(K, (V.shape[0], 3, 3))
    times = torch.from_numpy(timestamps_to_times(timestamps))
    return CameraPath(V, torch.from_numpy(np.ascontiguousarray(K)), int(width), int(height), times)
