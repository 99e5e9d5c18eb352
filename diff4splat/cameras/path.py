"""A camera path: T pinhole cameras (world-to-camera OpenCV viewmats, pixel Ks) with clip times."""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from diff4splat.cameras.intrinsics import center_crop_box
from diff4splat.scene.quaternions import ROTATION_TOL, quat_nlerp, quat_to_rotmat, rotation_errors, rotmat_to_quat
from diff4splat.utils.checks import check_finite, check_positive_int

__all__ = ["CameraPath", "invert_rigid", "camera_centers", "check_field_of_view", "MIN_FOV_DEG"]


def invert_rigid(viewmats: Tensor) -> Tensor:
    """Inverses (..., 4, 4), same dtype, of rigid transforms (..., 4, 4): [R | t; 0 0 0 1] → [Rᵀ | −Rᵀt; 0 0 0 1]."""
    R = viewmats[..., :3, :3]
    t = viewmats[..., :3, 3:]
    Rt = R.transpose(-1, -2)
    out = torch.zeros_like(viewmats)
    out[..., :3, :3] = Rt
    out[..., :3, 3:] = -Rt @ t
    out[..., 3, 3] = 1.0
    return out


def camera_centers(viewmats: Tensor) -> Tensor:
    """Camera centres c = −Rᵀt (..., 3), world frame, metres, dtype of ``viewmats``, of world-to-camera transforms
    (..., 4, 4) or (..., 3, 4); ValueError for another shape."""
    if not isinstance(viewmats, Tensor) or viewmats.dim() < 2 or tuple(viewmats.shape[-2:]) not in ((4, 4), (3, 4)):
        raise ValueError(f"viewmats must be a tensor of shape (..., 4, 4) or (..., 3, 4), got {_shape(viewmats)}")
    return -torch.einsum("...ji,...j->...i", viewmats[..., :3, :3], viewmats[..., :3, 3])


def _default_times(n: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    if n <= 1:
        return torch.zeros(max(n, 0), dtype=dtype, device=device)
    return torch.arange(n, dtype=dtype, device=device) / (n - 1)


@dataclass
class CameraPath:
    """T pinhole cameras along a clip (OpenCV frame: x right, y down, z forward), validated on construction.

    Attributes:
        viewmats: (T, 4, 4) world-to-camera rigid transforms [R | t], metres; T ≥ 1.
        Ks: (T, 3, 3) intrinsics, pixels ([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], fx, fy > 0).
        width, height: image size, pixels.
        times: (T,) clip times in [0, 1], non-decreasing; None → t_i = i/(T−1) (T = 1 → [0]) in ``viewmats``' dtype.
    """

    viewmats: Tensor
    Ks: Tensor
    width: int
    height: int
    times: Tensor | None = None

    def __post_init__(self) -> None:
        if self.times is None and isinstance(self.viewmats, Tensor) and self.viewmats.dim() == 3:
            self.times = _default_times(self.viewmats.shape[0], self.viewmats.dtype, self.viewmats.device)
        self.validate()

    def __len__(self) -> int:
        return int(self.viewmats.shape[0])

    def validate(self) -> None:
        """Check shapes and values.

        Raises:
            ValueError: naming the field: ``viewmats`` (not (T ≥ 1, 4, 4), non-finite, not a proper rotation within
                ROTATION_TOL, bottom row not [0, 0, 0, 1] within 1e-6), ``Ks`` (not (T, 3, 3), non-finite, fx or
                fy ≤ 0, not of the form above), ``width``/``height`` (not a positive int) or ``times`` (not (T,),
                non-finite, outside [0, 1], decreasing).
        """
        self.width = check_positive_int("width", self.width, "pixels")
        self.height = check_positive_int("height", self.height, "pixels")
        vm, K, times = self.viewmats, self.Ks, self.times
        if not isinstance(vm, Tensor) or vm.dim() != 3 or tuple(vm.shape[1:]) != (4, 4):
            raise ValueError(f"viewmats must be a tensor of shape (T, 4, 4), got {_shape(vm)}")
        T = vm.shape[0]
        if T == 0:
            raise ValueError("viewmats has zero frames; a camera path needs T ≥ 1")
        if not isinstance(K, Tensor) or tuple(K.shape) != (T, 3, 3):
            raise ValueError(f"Ks must be a tensor of shape ({T}, 3, 3), got {_shape(K)}")
        if not isinstance(times, Tensor) or tuple(times.shape) != (T,):
            raise ValueError(f"times must be a tensor of shape ({T},), got {_shape(times)}")
        for name, t in (("viewmats", vm), ("Ks", K), ("times", times)):
            if not t.is_floating_point():
                raise ValueError(f"{name} must be a floating-point tensor, got {t.dtype}")
            check_finite(name, t)

        vm64 = vm.detach().double()
        R = vm64[:, :3, :3]
        ortho_err, det_err = rotation_errors(R)
        bad = (ortho_err > ROTATION_TOL) | (det_err > ROTATION_TOL)
        if bool(bad.any()):
            i = int(bad.nonzero()[0])
            raise ValueError(
                f"viewmats[{i}] rotation is not a proper rotation: max |RᵀR−I|={float(ortho_err[i]):.3g}, "
                f"det R={float(torch.linalg.det(R[i])):.6g} (tolerance {ROTATION_TOL})"
            )
        bottom = vm64[:, 3, :] - vm64.new_tensor([0.0, 0.0, 0.0, 1.0])
        bad = bottom.abs().amax(-1) > 1e-6
        if bool(bad.any()):
            i = int(bad.nonzero()[0])
            raise ValueError(f"viewmats[{i}] bottom row must be [0, 0, 0, 1], got {vm64[i, 3].tolist()}")

        K64 = K.detach().double()
        bad = (K64[:, 0, 0] <= 0) | (K64[:, 1, 1] <= 0)
        if bool(bad.any()):
            i = int(bad.nonzero()[0])
            raise ValueError(f"Ks[{i}] focal lengths must be > 0 pixels, "
                             f"got fx={float(K64[i, 0, 0])}, fy={float(K64[i, 1, 1])}")
        structure = torch.stack([K64[:, 0, 1], K64[:, 1, 0], K64[:, 2, 0], K64[:, 2, 1], K64[:, 2, 2] - 1.0], -1)
        bad = structure.abs().amax(-1) > 1e-6
        if bool(bad.any()):
            i = int(bad.nonzero()[0])
            raise ValueError(f"Ks[{i}] must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], got {K64[i].tolist()}")

        if bool(((times < 0) | (times > 1)).any()):
            raise ValueError(f"times must lie in [0, 1], got min {float(times.min())}, max {float(times.max())}")
        if T > 1 and bool((times[1:] < times[:-1]).any()):
            i = int((times[1:] < times[:-1]).nonzero()[0]) + 1
            raise ValueError(f"times must be non-decreasing, but times[{i}]={float(times[i])} "
                             f"< times[{i - 1}]={float(times[i - 1])}")

    def camera_centers(self) -> Tensor:
        """(T, 3) camera centres in world coordinates, metres: c = −Rᵀ t (:func:`camera_centers`)."""
        return camera_centers(self.viewmats)

    def viewmat_at(self, t: float) -> Tensor:
        """World-to-camera pose (4, 4) at clip time ``t`` (finite, else ValueError), in ``viewmats``' dtype: between
        the bracketing cameras the centre is lerped and the camera-to-world rotation nlerped
        (:func:`~diff4splat.scene.quaternions.quat_nlerp`); outside the times the end pose is held; at a camera's own
        time a copy of its viewmat is returned.
        """
        t = float(t)
        if not math.isfinite(t):
            raise ValueError(f"t must be finite, got {t}")
        times = self.times.detach().double()
        k = int(torch.searchsorted(times, torch.tensor(t, dtype=torch.float64, device=times.device), right=True)) - 1
        if k < 0 or t == float(times[k]) or k == len(self) - 1:
            return self.viewmats[max(k, 0)].clone()  # a new tensor, as between key times (not a view of the path)
        w = (t - float(times[k])) / float(times[k + 1] - times[k])
        c2w = invert_rigid(self.viewmats[k:k + 2])
        q = rotmat_to_quat(c2w[:, :3, :3])
        out = torch.eye(4, dtype=self.viewmats.dtype, device=self.viewmats.device)
        out[:3, :3] = quat_to_rotmat(quat_nlerp(q[0], q[1], w))
        out[:3, 3] = (1 - w) * c2w[0, :3, 3] + w * c2w[1, :3, 3]
        return invert_rigid(out)

    def relative_to_first(self) -> CameraPath:
        """The same path in the first camera's frame: V_i' = V_i · V_0⁻¹ (V_0' = I exactly); images unchanged."""
        # an explicit sum of products, not a matmul: the same rounding whichever BLAS kernel a backend would pick
        rel = (self.viewmats[:, :, :, None] * invert_rigid(self.viewmats[:1])[:, None, :, :]).sum(dim=-2)
        rel[0] = torch.eye(4, dtype=rel.dtype, device=rel.device)  # exact, not V_0·V_0⁻¹ ≈ I
        return CameraPath(rel, self.Ks.clone(), self.width, self.height, self.times.clone())

    def resized(self, width: int, height: int) -> CameraPath:
        """The path for images stretched to ``width`` × ``height`` pixels (positive ints): fx, cx scale by
        width/W and fy, cy by height/H (a new aspect ratio gives non-square pixels)."""
        width, height = check_positive_int("width", width, "pixels"), check_positive_int("height", height, "pixels")
        scale = self.Ks.new_tensor([width / self.width, height / self.height, 1.0])
        Ks = self.Ks * scale[None, :, None]
        return CameraPath(self.viewmats.clone(), Ks, width, height, self.times.clone())

    def fitted(self, width: int, height: int) -> CameraPath:
        """The path for images centre-cropped to the aspect ratio of ``width`` × ``height`` as
        :func:`diff4splat.io.preprocess_image` crops them (:func:`center_crop_box`), then :meth:`resized`."""
        width, height = check_positive_int("width", width, "pixels"), check_positive_int("height", height, "pixels")
        y0, x0, ch, cw = center_crop_box(self.height, self.width, height, width)
        Ks = self.Ks.clone()
        Ks[:, 0, 2] -= x0
        Ks[:, 1, 2] -= y0
        return CameraPath(self.viewmats.clone(), Ks, cw, ch, self.times.clone()).resized(width, height)

    def to(self, *args, **kwargs) -> CameraPath:
        """Move/cast the tensors (``Tensor.to`` arguments)."""
        return CameraPath(self.viewmats.to(*args, **kwargs), self.Ks.to(*args, **kwargs), self.width, self.height,
                          self.times.to(*args, **kwargs))


def _shape(x: object) -> object:
    return tuple(x.shape) if hasattr(x, "shape") else type(x).__name__


MIN_FOV_DEG = 0.1
"""Narrowest field of view, degrees, of a camera of a path (0.1° is a ~20 m lens on a full-frame sensor)."""

def check_field_of_view(cameras: CameraPath) -> None:
    """Refuse a path with a camera narrower than :data:`MIN_FOV_DEG` (focal lengths in the wrong units).

    Raises:
        ValueError: naming the narrowest field of view and the focal lengths, pixels.
    """
    fx, fy = float(cameras.Ks[:, 0, 0].max()), float(cameras.Ks[:, 1, 1].max())
    fov = math.degrees(2 * math.atan(min(cameras.width / (2 * fx), cameras.height / (2 * fy))))
    if fov < MIN_FOV_DEG:
        raise ValueError(f"cameras: focal lengths fx={fx:.3g}, fy={fy:.3g} pixels give a field of view of {fov:.3g}° "
                         f"on a {cameras.width}×{cameras.height} image, below {MIN_FOV_DEG}° (check the intrinsics' "
                         f"units)")
