"""Loading input photographs (OpenCV decoding, centre crop, resize)."""
from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
import torch
from torch import Tensor

from ..cameras.intrinsics import center_crop_box

__all__ = ["load_image", "preprocess_image"]


def _check_size(size: tuple[int, int] | None) -> tuple[int, int] | None:
    if size is None:
        return None
    ok = isinstance(size, (tuple, list)) and len(size) == 2 and all(
        isinstance(s, int) and not isinstance(s, bool) and s > 0 for s in size
    )
    if not ok:
        raise ValueError(f"size must be (height, width) with positive ints, got {size!r}")
    return int(size[0]), int(size[1])


def _to_unit_float(array: np.ndarray) -> np.ndarray:
    """Integer or float image → float32 in [0, 1] (uint8 / 255, uint16 / 65535, floats checked)."""
    if array.dtype == np.uint8:
        return array.astype(np.float32) / 255.0
    if array.dtype == np.uint16:
        return array.astype(np.float32) / 65535.0
    if np.issubdtype(array.dtype, np.floating):
        out = array.astype(np.float32)
        if not np.isfinite(out).all():
            raise ValueError("image contains NaN or inf values")
        lo, hi = float(out.min()), float(out.max())
        if lo < -1e-6 or hi > 1 + 1e-6:
            raise ValueError(f"a floating-point image must lie in [0, 1], got range [{lo:.4g}, {hi:.4g}]")
        return np.clip(out, 0.0, 1.0)
    raise ValueError(f"image dtype must be uint8, uint16 or floating point, got {array.dtype}")


def preprocess_image(array: np.ndarray, size: tuple[int, int] | None = None) -> Tensor:
    """Convert an in-memory RGB(A)/grey image to a float RGB tensor, centre-cropped and resized.

    Steps: (1) scale to [0, 1] (uint8 / 255, uint16 / 65535, floats must already lie in [0, 1]);
    (2) grey → RGB by repeating the channel; alpha is composited over a white background,
    rgb·a + (1 − a), before any resampling (so transparent pixels never bleed colour);
    (3) centre-crop to the aspect ratio width/height of ``size`` (the crop keeps the full extent
    along the constrained axis, rounded to whole pixels); (4) resize with ``cv2.INTER_AREA`` when
    shrinking (area averaging, no aliasing) and ``cv2.INTER_LINEAR`` when enlarging (OpenCV's
    INTER_AREA degenerates to nearest-neighbour blocks for integer up-scaling).

    Args:
        array: (H, W), (H, W, 1) grey, (H, W, 2) grey+alpha, (H, W, 3) RGB or (H, W, 4) RGBA;
            uint8, uint16 or float in [0, 1]. Channel order is RGB (not OpenCV's BGR).
        size: (height, width) of the output in pixels; ``None`` keeps the input size (no crop).

    Returns:
        (height, width, 3) float32 tensor in [0, 1], RGB.

    Raises:
        ValueError: bad ``size``, a shape or dtype listed as unsupported above, an empty image,
            or non-finite / out-of-range float values.
    """
    size = _check_size(size)
    array = np.asarray(array)
    if array.ndim == 2:
        array = array[..., None]
    if array.ndim != 3 or array.shape[-1] not in (1, 2, 3, 4):
        raise ValueError(f"image must have shape (H, W) or (H, W, C) with C in 1..4, got {array.shape}")
    if array.shape[0] == 0 or array.shape[1] == 0:
        raise ValueError(f"image is empty, shape {array.shape}")
    img = _to_unit_float(array)
    c = img.shape[-1]
    color = img[..., :1].repeat(3, axis=-1) if c in (1, 2) else img[..., :3]
    if c in (2, 4):
        alpha = img[..., -1:]
        color = color * alpha + (1.0 - alpha)  # composite over white
    if size is not None:
        h, w = size
        y0, x0, ch, cw = center_crop_box(*color.shape[:2], h, w)
        color = color[y0 : y0 + ch, x0 : x0 + cw]
        if (ch, cw) != (h, w):
            interp = cv2.INTER_AREA if (h <= ch and w <= cw) else cv2.INTER_LINEAR
            color = cv2.resize(np.ascontiguousarray(color), (w, h), interpolation=interp)
    return torch.from_numpy(np.ascontiguousarray(np.clip(color, 0.0, 1.0), dtype=np.float32))


def load_image(path: str | os.PathLike, size: tuple[int, int] | None = None) -> Tensor:
    """Read an image file with OpenCV and preprocess it (:func:`preprocess_image`).

    Any format OpenCV decodes (PNG, JPEG, TIFF, WebP, BMP, …) in 8 or 16 bits, grey, RGB or RGBA.
    Alpha is composited over white. Images without alpha are decoded a second time with
    ``IMREAD_ANYDEPTH | IMREAD_ANYCOLOR`` so that the EXIF orientation tag is applied (OpenCV's
    ``IMREAD_UNCHANGED``, needed to keep alpha and 16 bits, ignores it).

    Args:
        path: image file.
        size: (height, width) in pixels, or ``None`` to keep the file's size.

    Returns:
        (height, width, 3) float32 tensor in [0, 1], RGB.

    Raises:
        FileNotFoundError: ``path`` is not an existing file.
        ValueError: the file cannot be decoded as an image, or a bad ``size``.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"image file not found: {path}")
    size = _check_size(size)
    data = np.fromfile(path, dtype=np.uint8)
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if img is None:
        raise ValueError(f"could not decode {path} as an image (OpenCV)")
    if img.ndim == 2 or img.shape[-1] in (1, 3):
        oriented = cv2.imdecode(data, cv2.IMREAD_ANYDEPTH | cv2.IMREAD_ANYCOLOR)
        if oriented is not None and oriented.dtype == img.dtype:
            img = oriented
    if img.ndim == 3 and img.shape[-1] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    elif img.ndim == 3 and img.shape[-1] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGBA)
    return preprocess_image(img, size)
