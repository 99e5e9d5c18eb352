"""Pinhole intrinsics in pixels (OpenCV convention, pixel (i, j) centred at (j+0.5, i+0.5)): K = [[fx, 0, cx],
[0, fy, cy], [0, 0, 1]] maps a camera-frame point (x, y, z) to (fx·x/z + cx, fy·y/z + cy); the principal point
defaults to the image centre (W/2, H/2) (Hartley & Zisserman, *Multiple View Geometry*, §6.1).
"""
from __future__ import annotations

import math

import torch
from torch import Tensor

from diff4splat.utils.checks import check_positive, check_positive_int

__all__ = ["center_crop_box", "intrinsics_from_fov", "intrinsics_from_focal", "fov_from_intrinsics"]


def _check_fov(name: str, value: float) -> float:
    v = check_positive(name, value)
    if v >= 180.0:
        raise ValueError(f"{name} must lie in (0, 180) degrees, got {value!r}")
    return v


def intrinsics_from_focal(
    fx: float,
    fy: float,
    width: int,
    height: int,
    cx: float | None = None,
    cy: float | None = None,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str = "cpu",
) -> Tensor:
    """(3, 3) pinhole K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], pixels, from focal lengths ``fx``, ``fy`` > 0 pixels,
    the image size (positive ints) and a principal point (any finite value; None → the image centre).

    Raises:
        ValueError: naming ``fx``/``fy`` (not positive and finite), ``width``/``height`` (not a positive int) or
            ``cx``/``cy`` (not finite).
    """
    fx = check_positive("fx", fx)
    fy = check_positive("fy", fy)
    width = check_positive_int("width", width, "pixels")
    height = check_positive_int("height", height, "pixels")
    cx = width / 2.0 if cx is None else float(cx)
    cy = height / 2.0 if cy is None else float(cy)
    for name, v in (("cx", cx), ("cy", cy)):
        if not math.isfinite(v):
            raise ValueError(f"{name} must be finite, got {v!r}")
    return torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=dtype, device=device)


def intrinsics_from_fov(
    width: int,
    height: int,
    *,
    fov_x_deg: float | None = None,
    fov_y_deg: float | None = None,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str = "cpu",
) -> Tensor:
    """(3, 3) pinhole K, pixels, principal point at the image centre, from a field of view edge to edge in degrees,
    in (0, 180): fx = (W/2) / tan(fov_x/2), fy = (H/2) / tan(fov_y/2) (Hartley & Zisserman §6.1). With one of the
    two given the pixels are square.

    Raises:
        ValueError: naming ``fov_x_deg``/``fov_y_deg`` (neither given, or outside (0, 180)) or ``width``/``height``.
    """
    width = check_positive_int("width", width, "pixels")
    height = check_positive_int("height", height, "pixels")
    if fov_x_deg is None and fov_y_deg is None:
        raise ValueError("fov_x_deg or fov_y_deg must be given (degrees in (0, 180)), got neither")
    fx = fy = None
    if fov_x_deg is not None:
        fx = (width / 2.0) / math.tan(math.radians(_check_fov("fov_x_deg", fov_x_deg)) / 2.0)
    if fov_y_deg is not None:
        fy = (height / 2.0) / math.tan(math.radians(_check_fov("fov_y_deg", fov_y_deg)) / 2.0)
    fx = fy if fx is None else fx
    fy = fx if fy is None else fy
    return intrinsics_from_focal(fx, fy, width, height, dtype=dtype, device=device)


def fov_from_intrinsics(K: Tensor, width: int, height: int) -> tuple[float, float]:
    """(fov_x_deg, fov_y_deg), each in (0, 180), of a centred pinhole K (3, 3), pixels: fov = 2·atan((size/2) / f),
    the inverse of :func:`intrinsics_from_fov`.

    Raises:
        ValueError: naming ``K`` (not (3, 3), focal lengths not > 0) or ``width``/``height``.
    """
    if tuple(K.shape) != (3, 3):
        raise ValueError(f"K must have shape (3, 3), got {tuple(K.shape)}")
    fx, fy = float(K[0, 0]), float(K[1, 1])
    if not (fx > 0 and fy > 0):
        raise ValueError(f"K must have positive focal lengths, got fx={fx}, fy={fy}")
    width = check_positive_int("width", width, "pixels")
    height = check_positive_int("height", height, "pixels")
    return math.degrees(2.0 * math.atan(width / 2.0 / fx)), math.degrees(2.0 * math.atan(height / 2.0 / fy))


def center_crop_box(height: int, width: int, target_height: int, target_width: int) -> tuple[int, int, int, int]:
    """(y0, x0, crop_height, crop_width), pixels: the largest centred crop of a height×width image with the target's
    aspect ratio, used for photographs (:func:`diff4splat.io.preprocess_image`) and their intrinsics
    (:meth:`diff4splat.cameras.CameraPath.fitted`) alike."""
    if width * target_height > height * target_width:  # wider than the target: crop columns
        ch, cw = height, max(1, min(width, round(height * target_width / target_height)))
    else:  # taller: crop rows
        ch, cw = max(1, min(height, round(width * target_height / target_width))), width
    return (height - ch) // 2, (width - cw) // 2, ch, cw
