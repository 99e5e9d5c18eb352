"""A depth map of the photograph, from a file the user made elsewhere (``generate --depth``).

Formats, by extension:

- ``.exr``: the "Z" channel (:func:`diff4splat.io.load_depth_exr`; what ``generate`` itself writes);
- ``.npy``: a 2-D float array (or (H, W, 1)), no pickles;
- ``.png`` / ``.tif`` / ``.tiff``: one grey channel, 16-bit (8-bit only for relative kinds). A 16-bit metric map is
  in millimetres (the Kinect / ScanNet / TUM convention) and is divided by 1000.

Values that are NaN, ±inf or not positive are holes (0 is the usual "no depth" of 16-bit maps); the pipeline fills
them from the network's depth. The map is cropped like the photograph (:func:`diff4splat.cameras.center_crop_box`
on the photograph's displayed size when the map has that size, else on its own) and resized to the output resolution
with nearest-neighbour sampling (no depth is invented between a foreground and a background pixel).
"""
from __future__ import annotations

import os

import cv2
import numpy as np
import torch
from torch import Tensor

from ..cameras import center_crop_box
from .exr import load_depth_exr
from .inputs import check_input_file

__all__ = ["DEPTH_SUFFIXES", "MILLIMETRES", "read_depth_map", "fit_depth_map"]

DEPTH_SUFFIXES = (".exr", ".npy", ".png", ".tif", ".tiff")
"""File types ``--depth`` reads."""
MILLIMETRES = 1e-3
"""Metres per unit of a 16-bit metric depth image."""


def read_depth_map(path: str | os.PathLike, kind: str = "metric", what: str = "--depth") -> np.ndarray:
    """Read a depth map file (module docstring) as it is stored, scaled to metres for a metric 16-bit image.

    Args:
        path: the file.
        kind: "metric", "relative" or "inverse" (:data:`diff4splat.assemble.DEPTH_KINDS`): an 8-bit image is refused
            for "metric", a 16-bit one is read as millimetres for "metric".
        what: the argument's name for messages.

    Returns:
        (H, W) float64 array; holes as they are in the file (NaN/inf/0/negative).

    Raises:
        FileNotFoundError / ValueError: a missing or unreadable file, an unknown extension, not one channel, an 8-bit
            image for metric depth, no finite positive value (each message names the file).
    """
    path = check_input_file(path, what)
    suffix = path.suffix.lower()
    if suffix not in DEPTH_SUFFIXES:
        raise ValueError(f"{what}: {path} is not a depth map this reads ({', '.join(DEPTH_SUFFIXES)})")
    if suffix == ".exr":
        try:
            depth = load_depth_exr(path).astype(np.float64)
        except ValueError as e:
            raise ValueError(f"{what}: {e}") from None
    elif suffix == ".npy":
        try:
            depth = np.load(path, allow_pickle=False)
        except (ValueError, OSError, EOFError) as e:
            raise ValueError(f"{what}: {path} is not a readable .npy array ({e})") from None
        if depth.ndim == 3 and depth.shape[-1] == 1:
            depth = depth[..., 0]
        if depth.ndim != 2 or not np.issubdtype(depth.dtype, np.number):
            raise ValueError(f"{what}: {path} must hold a 2-D numeric array, got {depth.dtype} {depth.shape}")
        depth = depth.astype(np.float64)
    else:
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if raw is None:
            raise ValueError(f"{what}: {path} is not a readable image")
        if raw.ndim == 3 and raw.shape[-1] == 1:
            raw = raw[..., 0]
        if raw.ndim != 2:
            raise ValueError(f"{what}: {path} must be a one-channel (grey) image, got {raw.shape[-1]} channels")
        if raw.dtype == np.uint8 and kind == "metric":
            raise ValueError(f"{what}: {path} is 8-bit; metric depth needs a 16-bit image (millimetres), an EXR or "
                             f"a .npy (or give --depth-kind relative/inverse)")
        depth = raw.astype(np.float64) * (MILLIMETRES if raw.dtype == np.uint16 and kind == "metric" else 1.0)
    if not np.any(np.isfinite(depth) & (depth > 0)):
        raise ValueError(f"{what}: {path} holds no finite positive depth")
    return depth


def fit_depth_map(depth: np.ndarray, photo_shape: tuple[int, int], size: tuple[int, int]) -> tuple[Tensor, str | None]:
    """Crop and resize a depth map to the output resolution as the photograph was (module docstring).

    Args:
        depth: (h, w) the map as read.
        photo_shape: (H_p, W_p) the photograph's displayed size.
        size: (H, W) the output resolution.

    Returns:
        ((H, W) float32 CPU tensor, a note saying what was resized or None when the map had the photograph's size
        already at the output resolution).
    """
    H, W = size
    h, w = depth.shape
    y0, x0, ch, cw = center_crop_box(h, w, H, W)
    cropped = np.ascontiguousarray(depth[y0:y0 + ch, x0:x0 + cw])
    out = cv2.resize(cropped, (W, H), interpolation=cv2.INTER_NEAREST) if (ch, cw) != (H, W) else cropped
    note = None
    if (h, w) != (H, W):
        note = (f"depth map {w}×{h} resized to {W}×{H}" + ("" if (h, w) == tuple(photo_shape) else
                f" (the photograph is {photo_shape[1]}×{photo_shape[0]}: check that the map is of this photograph)"))
    return torch.from_numpy(out.astype(np.float32)), note
