"""A depth map of the photograph from a file the user made elsewhere (``generate --depth``): ``.exr`` ("Z"
channel), ``.npy`` (2-D, no pickles) or a one-channel ``.png``/``.tif``/``.tiff`` (16-bit; 8-bit only for relative
kinds; a 16-bit metric map is millimetres, the Kinect / ScanNet / TUM convention). Non-finite values, metric values
outside [1 mm, 10 km] and non-positive disparities are holes, filled from the network's depth (:func:`valid_depth`).
The map is cropped like the photograph and resized with nearest-neighbour sampling (:func:`fit_depth_map`).
"""
from __future__ import annotations

import os

import cv2
import numpy as np
import torch
from torch import Tensor

from diff4splat.cameras import center_crop_box
from diff4splat.io.exr import load_depth_exr
from diff4splat.io.inputs import check_input_file

__all__ = ["DEPTH_SUFFIXES", "MILLIMETRES", "MIN_METRIC_DEPTH", "MAX_METRIC_DEPTH", "read_depth_map", "fit_depth_map",
           "valid_depth", "check_depth_values"]

DEPTH_SUFFIXES = (".exr", ".npy", ".png", ".tif", ".tiff")
"""File types ``--depth`` reads."""
MILLIMETRES = 1e-3
"""Metres per unit of a 16-bit metric depth image."""
MIN_METRIC_DEPTH = 1e-3
"""Nearest metric depth taken from a map, metres (1 mm); nearer values are holes."""
MAX_METRIC_DEPTH = 1e4
"""Farthest metric depth taken from a map, metres (10 km); farther values ("no surface", sky) are holes."""


def valid_depth(depth: Tensor, kind: str = "metric") -> Tensor:
    """Mask of the pixels carrying depth: finite, and for ``metric`` within [:data:`MIN_METRIC_DEPTH`,
    :data:`MAX_METRIC_DEPTH`] metres, for ``inverse`` positive (``relative``: any finite value)."""
    mask = torch.isfinite(depth)
    if kind == "metric":
        mask &= (depth >= MIN_METRIC_DEPTH) & (depth <= MAX_METRIC_DEPTH)
    elif kind == "inverse":
        mask &= depth > 0
    return mask


def check_depth_values(depth: Tensor, kind: str, what: str = "depth") -> None:
    """Check a depth map (H, W) (metres for ``metric``; ``kind`` "metric", "relative" or "inverse") before any
    network runs: it must have valid pixels (:func:`valid_depth`), and a relative/inverse map must vary over them.

    Raises:
        ValueError: prefixed with ``what`` (the argument and file): no valid pixel (naming the values' range), or a
            constant relative/inverse map.
    """
    mask = valid_depth(depth, kind)
    finite = depth[torch.isfinite(depth)]
    span = f"{float(finite.min()):.4g} … {float(finite.max()):.4g}" if finite.numel() else "none finite"
    if not bool(mask.any()):
        need = {"metric": f"metres in [{MIN_METRIC_DEPTH:g}, {MAX_METRIC_DEPTH:g}] (a 16-bit image: millimetres)",
                "inverse": "positive disparity", "relative": "finite values"}[kind]
        raise ValueError(f"{what} holds no usable {kind} depth: its values ({span}) are not {need}")
    values = depth[mask]
    if kind != "metric" and float(values.max() - values.min()) == 0:
        raise ValueError(f"{what}: a {kind} depth map must vary, but every valid value is {float(values[0]):.6g}: its "
                         "scale and shift cannot be fitted to the network's depth (a flat map of metres is "
                         "--depth-kind metric)")


def read_depth_map(path: str | os.PathLike, kind: str = "metric", what: str = "--depth") -> np.ndarray:
    """Read a depth map file (module docstring) as (H, W) float64 as stored (holes included), a 16-bit metric image
    scaled to metres. ``kind``: :data:`diff4splat.assembly.assemble.DEPTH_KINDS`; ``what``: the flag in messages.

    Raises:
        FileNotFoundError / ValueError: naming the file: missing or unreadable, an unknown extension, not one
            channel, 8-bit for metric depth, or values :func:`check_depth_values` refuses.
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
    check_depth_values(torch.from_numpy(depth), kind, f"{what} {path}")
    return depth


def fit_depth_map(depth: np.ndarray, photo_shape: tuple[int, int], size: tuple[int, int]) -> tuple[Tensor, str | None]:
    """Centre-crop and resize (nearest) a depth map (h, w) to ``size`` (H, W) as the photograph was.

    Returns:
        ((H, W) float32 CPU tensor, a note on the resize (and on a size that is not ``photo_shape``), or None when
        the map had the output size).
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
