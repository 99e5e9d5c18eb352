"""MP4 video and PNG image writing with OpenCV (atomic), and MP4 reading for tests and tools."""
from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
from torch import Tensor

from diff4splat.io.atomic import atomic_output_path
from diff4splat.utils.checks import check_positive
from diff4splat.utils.devices import host_values
from diff4splat.utils.errors import quiet_c_stderr

__all__ = ["save_video", "load_video", "save_image", "to_uint8", "check_fps", "check_video_size", "MAX_FPS",
           "DEFAULT_FPS", "MAX_VIDEO_SIDE"]

DEFAULT_FPS = 8.0
"""Frame rate of every video, viewer and output folder when none is given, frames per second."""

MAX_VIDEO_SIDE = 8190
"""Largest width or height :func:`save_video` writes, pixels (MPEG-4 Part 2 codes each in 13 bits; sizes are even)."""
MAX_FPS = 1000
"""Highest frame rate :func:`save_video` writes (MPEG-4 Part 2's time base holds at most 65535 ticks per second)."""


def check_fps(fps: object, name: str = "fps") -> float:
    """``fps`` as a float if it is a finite number in (0, :data:`MAX_FPS`], else ValueError naming ``name``."""
    fps = check_positive(name, fps)
    if fps > MAX_FPS:
        raise ValueError(f"{name} must be at most {MAX_FPS} frames per second (the MP4 encoder's limit is "
                         f"65535), got {fps:g}")
    return fps


def to_uint8(images: Tensor | np.ndarray, name: str = "images") -> np.ndarray:
    """Images of any shape (array or tensor, any device) as a numpy uint8 array: uint8 as is, floats as
    round(255·clip(x, 0, 1)) (rendered SH colours can exceed 1); ValueError naming ``name`` for another dtype or
    NaN/inf."""
    if isinstance(images, Tensor):
        images = host_values(images).numpy()
    images = np.asarray(images)
    if images.dtype == np.uint8:
        return images
    if not np.issubdtype(images.dtype, np.floating):
        raise ValueError(f"{name} must be uint8 or floating point in [0, 1], got dtype {images.dtype}")
    flat = np.ascontiguousarray(images).reshape(-1)
    out = np.empty(flat.shape, np.uint8)
    for start in range(0, flat.size, _CHUNK):  # chunks: no full-size float temporaries
        x = flat[start:start + _CHUNK]
        if not np.isfinite(x).all():
            raise ValueError(f"{name} contains NaN or inf values")
        x = np.clip(x, 0.0, 1.0)
        x *= 255.0
        out[start:start + _CHUNK] = np.rint(x, out=x)
    return out.reshape(images.shape)


_CHUNK = 1 << 20
"""Values :func:`to_uint8` converts at a time."""


def check_video_size(width: int, height: int, knobs: str = "the output size") -> None:
    """ValueError (naming ``knobs``, what sets the size) if an MP4 of ``width`` × ``height``, odd sides padded to
    even, would exceed :data:`MAX_VIDEO_SIDE`: checked before the frames are made."""
    w, h = int(width) + int(width) % 2, int(height) + int(height) % 2
    if max(w, h) > MAX_VIDEO_SIDE:
        raise ValueError(f"a video of {width}×{height} pixels cannot be written: MPEG-4 allows at most "
                         f"{MAX_VIDEO_SIDE} pixels a side; lower {knobs}")


def save_video(path: str | os.PathLike, frames: Tensor | np.ndarray, fps: float = DEFAULT_FPS) -> None:
    """Write RGB frames to an MP4 file (MPEG-4 Part 2, OpenCV fourcc ``mp4v``; lossy, 8-bit 4:2:0), atomically.

    Args:
        path: output file ending in ``.mp4``.
        frames: (T, H, W, 3) RGB, uint8 or float in [0, 1] (:func:`to_uint8`), T ≥ 1, H and W even and at most
            :data:`MAX_VIDEO_SIDE` (odd sizes are refused, not cropped).
        fps: frames per second, in (0, :data:`MAX_FPS`].

    Raises:
        ValueError: naming ``path`` (suffix), ``frames`` (shape, dtype, odd or too large a size, NaN) or ``fps``.
        OSError: naming ``path`` (disk full, read-only, permissions; :func:`~diff4splat.io.atomic.naming_os_errors`).
        RuntimeError: OpenCV could not open the encoder, or the file it wrote does not hold every frame.
    """
    path = Path(path)
    if path.suffix.lower() != ".mp4":
        raise ValueError(f"path must end in .mp4, got {str(path)!r}")
    fps = check_fps(fps)
    video = to_uint8(frames, "frames")
    if video.ndim != 4 or video.shape[-1] != 3 or video.shape[0] < 1:
        raise ValueError(f"frames must have shape (T, H, W, 3) with T ≥ 1, got {video.shape}")
    T, H, W, _ = video.shape
    if H % 2 or W % 2 or H == 0 or W == 0:
        raise ValueError(f"frames height and width must be positive and even for MP4, got {H}×{W}")
    check_video_size(W, H, "the frames' size")
    with atomic_output_path(path) as tmp:  # its RuntimeErrors become OSError(ENOSPC, …, path) on a full disk
        writer = cv2.VideoWriter(tmp, cv2.VideoWriter_fourcc(*"mp4v"), float(fps), (W, H))
        if not writer.isOpened():
            raise RuntimeError(f"OpenCV could not open an mp4v video writer for {path}")
        try:
            for frame in video:
                writer.write(np.ascontiguousarray(frame[..., ::-1]))  # RGB → BGR
        finally:
            writer.release()
        written = _frame_count(tmp)
        if written != T:  # OpenCV reports no write error: a disk that filled up leaves a short, unreadable file
            raise RuntimeError(f"OpenCV wrote {written} of {T} frames to {path}")


def _frame_count(path: str) -> int:
    """Frames the container at ``path`` says it holds (0 when it cannot be opened, e.g. truncated)."""
    with quiet_c_stderr():  # FFmpeg's "moov atom not found" on a truncated file
        cap = cv2.VideoCapture(path)
        try:
            return int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) if cap.isOpened() else 0
        finally:
            cap.release()


def load_video(path: str | os.PathLike) -> np.ndarray:
    """Every frame of a video file OpenCV reads, as (T, H, W, 3) uint8 RGB.

    Raises:
        FileNotFoundError: ``path`` is not an existing file.
        ValueError: no frame could be decoded.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"video file not found: {path}")
    frames = []
    with quiet_c_stderr():  # FFmpeg's complaints about a corrupt file; the ValueError below names it
        cap = cv2.VideoCapture(str(path))
        try:
            while True:
                ok, frame = cap.read()
                if not ok:
                    break
                frames.append(cv2.cvtColor(frame, cv2.COLOR_BGR2RGB))
        finally:
            cap.release()
    if not frames:
        raise ValueError(f"video file {path}: could not decode any frame (not a video OpenCV reads, or corrupt)")
    return np.stack(frames)


def save_image(path: str | os.PathLike, image: Tensor | np.ndarray) -> None:
    """Write an 8-bit image atomically, in the format of ``path``'s suffix (PNG is lossless; any OpenCV writes).
    ``image``: (H, W, 3) RGB, (H, W, 4) RGBA or (H, W) grey; uint8 or float in [0, 1] (clipped).

    Raises:
        ValueError: naming ``path`` (a suffix OpenCV cannot write) or ``image`` (shape, dtype, NaN, or refused by
            the encoder).
        OSError: naming ``path`` (disk full, read-only, permissions).
    """
    path = Path(path)
    if not cv2.haveImageWriter(str(path)):
        raise ValueError(f"path must have an image suffix OpenCV can write (e.g. .png), got {str(path)!r}")
    img = to_uint8(image, "image")
    if img.ndim == 3 and img.shape[-1] == 1:
        img = img[..., 0]
    if img.ndim == 3 and img.shape[-1] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    elif img.ndim == 3 and img.shape[-1] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_RGBA2BGRA)
    elif img.ndim != 2:
        raise ValueError(f"image must have shape (H, W), (H, W, 3) or (H, W, 4), got {img.shape}")
    if img.shape[0] == 0 or img.shape[1] == 0:
        raise ValueError(f"image is empty, shape {img.shape}")
    with quiet_c_stderr():
        ok, data = cv2.imencode(path.suffix, np.ascontiguousarray(img))
    if not ok:
        raise ValueError(f"image: OpenCV cannot encode a {img.shape} {img.dtype} image as {path.suffix}")
    with atomic_output_path(path) as tmp, open(tmp, "wb") as f:  # Python's write reports a full disk; imwrite does not
        f.write(data.tobytes())
