"""Depth maps as OpenEXR files (float32 channel "Z", optional "A"), via the OpenEXR 3.x Python API."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import OpenEXR
from torch import Tensor

from diff4splat.io.atomic import atomic_output_path
from diff4splat.utils.devices import host_values

__all__ = ["save_depth_exr", "load_depth_exr"]


def _as_float32_map(name: str, x: Tensor | np.ndarray) -> np.ndarray:
    if isinstance(x, Tensor):
        x = host_values(x).numpy()
    x = np.asarray(x)
    if x.ndim != 2 or x.shape[0] == 0 or x.shape[1] == 0:
        raise ValueError(f"{name} must have shape (H, W) with H, W ≥ 1, got {x.shape}")
    if not (np.issubdtype(x.dtype, np.floating) or np.issubdtype(x.dtype, np.integer)):
        raise ValueError(f"{name} must be numeric, got dtype {x.dtype}")
    return np.ascontiguousarray(x, dtype=np.float32)


def save_depth_exr(
    path: str | os.PathLike,
    depth: Tensor | np.ndarray,  # (H, W) metres
    alpha: Tensor | np.ndarray | None = None,  # (H, W) in [0, 1]
) -> None:
    """Write a depth map as a single-part scanline EXR atomically (ZIP compression, lossless float32): the depth in
    the standard channel "Z" (distance along the view axis), the coverage, if any, in "A".

    Args:
        depth: (H, W) z-depth, metres, ≥ 0 or +inf (background).
        alpha: (H, W) accumulated opacity in [0, 1], or None for no "A" channel.

    Raises:
        ValueError: naming ``depth`` (shape, NaN, negative) or ``alpha`` (shape, non-finite, outside [0, 1]).
        OSError: naming ``path`` (disk full, read-only, permissions; :func:`~diff4splat.io.atomic.naming_os_errors`).
        RuntimeError: OpenEXR wrote a file that does not read back.
    """
    z = _as_float32_map("depth", depth)
    if np.isnan(z).any():
        raise ValueError("depth contains NaN; set pixels without geometry to 0 or +inf")
    if (z < 0).any():
        raise ValueError(f"depth must be ≥ 0 metres, min is {float(z.min())}")
    channels = {"Z": z}
    if alpha is not None:
        a = _as_float32_map("alpha", alpha)
        if a.shape != z.shape:
            raise ValueError(f"alpha must have the shape of depth {z.shape}, got {a.shape}")
        if not np.isfinite(a).all() or (a < 0).any() or (a > 1).any():
            raise ValueError("alpha must be finite and lie in [0, 1]")
        channels["A"] = a
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_output_path(path) as tmp:  # its RuntimeErrors become OSError(ENOSPC, …, path) on a full disk
        with OpenEXR.File(header, channels) as f:
            f.write(tmp)
        try:  # OpenEXR may miss a failed last flush: read the file back (a few ms) rather than keep a short one
            with OpenEXR.File(tmp, separate_channels=True) as f:
                complete = all(np.array(ch.pixels).shape == z.shape for ch in f.channels().values())
        except Exception as e:
            raise RuntimeError(f"OpenEXR wrote an unreadable {path}: {e}") from e
        if not complete:
            raise RuntimeError(f"OpenEXR wrote an incomplete {path}")


EXR_MAGIC = b"\x76\x2f\x31\x01"
"""The first four bytes of every OpenEXR file (the format's magic number, 20000630)."""
_OTHER_FORMATS = ((b"\x89PNG", "PNG image"), (b"\xff\xd8\xff", "JPEG image"), (b"II*\x00", "TIFF image"),
                  (b"MM\x00*", "TIFF image"), (b"\x93NUMPY", "NumPy .npy array"), (b"PK\x03\x04", "zip archive"),
                  (b"GIF8", "GIF image"), (b"BM", "BMP image"))
"""Signatures of the files most often given an .exr name by mistake, for the error message."""


def load_depth_exr(
    path: str | os.PathLike, return_alpha: bool = False
) -> np.ndarray | tuple[np.ndarray, np.ndarray | None]:
    """The "Z" channel (H, W) float32, metres, of an EXR (:func:`save_depth_exr`'s or any), and with
    ``return_alpha`` its "A" channel (H, W) float32 or None; half floats are converted.

    Raises:
        FileNotFoundError: ``path`` is not an existing file.
        ValueError: not a readable EXR (naming the format it holds, when known) or no "Z" channel.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"EXR file not found: {path}")
    with open(path, "rb") as f:
        head = f.read(8)
    if head[:4] != EXR_MAGIC:
        kind = next((name for magic, name in _OTHER_FORMATS if head.startswith(magic)), None)
        raise ValueError(f"{path} is not an OpenEXR file: " +
                         (f"it holds a {kind}" if kind else "it does not start with the EXR signature 76 2f 31 01") +
                         (" (empty)" if not head else ""))
    try:
        with OpenEXR.File(str(path), separate_channels=True) as f:
            channels = {name: np.array(ch.pixels) for name, ch in f.channels().items()}
    except Exception as e:  # OpenEXR raises RuntimeError/IOError subclasses for corrupt files
        raise ValueError(f"could not read {path} as an OpenEXR file: {e}") from e
    if "Z" not in channels:
        raise ValueError(f"{path} has no depth channel 'Z' (channels: {sorted(channels)})")
    depth = channels["Z"].astype(np.float32)
    if not return_alpha:
        return depth
    alpha = channels["A"].astype(np.float32) if "A" in channels else None
    return depth, alpha
