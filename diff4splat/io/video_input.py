"""A clip of the user's video: frames ``start, start + stride, …`` of a video file (any container and codec OpenCV's
backend reads) or of a folder of images (sorted by name), decoded once, only up to the last frame needed.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from diff4splat.io.image import check_image_pixels, read_image
from diff4splat.utils.checks import check_positive_int
from diff4splat.utils.errors import quiet_c_stderr

__all__ = ["VideoClip", "IMAGE_SUFFIXES", "check_clip_request", "read_video_clip"]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")
"""Files of a frame folder, by suffix (case-insensitive); other files in the folder are ignored."""


@dataclass(frozen=True)
class VideoClip:
    """Frames read by :func:`read_video_clip`.

    Attributes:
        frames: T arrays (H, W, 3) uint8 RGB (a video file), or as :func:`~diff4splat.io.image.read_image` returns
            them (a folder).
        indices: (T,) the frames' indices in the source (0 = its first frame).
        fps: the file's frame rate, frames per second, or None (a folder, or a file that does not say).
        total: the source's frame count (a folder's images; the frame count a video file's header states), or None
            when a video file does not state it.
    """

    frames: list[np.ndarray]
    indices: list[int]
    fps: float | None
    total: int | None = None


def check_clip_request(frames: object, stride: object, start: object) -> tuple[int | None, int, int]:
    """``(frames, stride, start)`` as ints: frames ≥ 2 (None: the caller's default), stride ≥ 1, start ≥ 0.

    Raises:
        ValueError: naming the flag (``--frames``, ``--stride``, ``--start``) and the value.
    """
    if frames is not None and check_positive_int("--frames", frames) < 2:
        raise ValueError(f"--frames {frames}: a clip needs at least 2 frames "
                         f"(a frame count the VAE takes: 5, 9, 13, …)")
    stride = check_positive_int("--stride", stride)
    if isinstance(start, bool) or not isinstance(start, (int, np.integer)) or int(start) < 0:
        raise ValueError(f"--start must be an integer ≥ 0, got {start!r}")
    return None if frames is None else int(frames), stride, int(start)


def _short(path: Path, found: int, start: int, stride: int, frames: int) -> ValueError:
    need = start + stride * (frames - 1) + 1
    return ValueError(f"{path}: {found} frame(s), but --start {start} --stride {stride} --frames {frames} needs {need}")


def read_video_clip(path: str | os.PathLike, frames: int, stride: int = 1, start: int = 0) -> VideoClip:
    """Frames ``start + stride·i`` (i < ``frames``, :func:`check_clip_request`) of a video file or of a folder whose
    image files (:data:`IMAGE_SUFFIXES`) are the frames in name order.

    Raises:
        FileNotFoundError: nothing at ``path``.
        ValueError: a bad request, a file OpenCV cannot decode, a folder without images, frames of different sizes,
            a frame above the ``image_pixels`` limit, fewer frames than the request needs.
    """
    frames, stride, start = check_clip_request(frames, stride, start)
    if frames is None:
        raise ValueError("--frames: a clip's frame count must be given (an int ≥ 2)")
    path = Path(path)
    wanted = [start + stride * i for i in range(frames)]
    if path.is_dir():
        files = sorted(p for p in path.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
        if not files:
            raise ValueError(f"{path}: no image file ({', '.join(IMAGE_SUFFIXES)}) in the folder")
        if wanted[-1] >= len(files):
            raise _short(path, len(files), start, stride, frames)
        images = [read_image(files[i]) for i in wanted]
        fps, total = None, len(files)
    elif path.is_file():
        images, fps, total = _decode(path, wanted, start, stride, frames)
    else:
        raise FileNotFoundError(f"video not found: {path}")
    if len({im.shape[:2] for im in images}) > 1:
        raise ValueError(f"{path}: the frames differ in size ({sorted({im.shape[:2] for im in images})})")
    return VideoClip(images, wanted, fps, total)


def _decode(path: Path, wanted: list[int], start: int, stride: int,
            frames: int) -> tuple[list[np.ndarray], float | None, int | None]:
    """The frames ``wanted`` of a video file (decoding stops after the last), its frame rate and the frame count its
    header states (None if it states none, or fewer frames than were decoded)."""
    images, index, keep = [], 0, set(wanted)
    with quiet_c_stderr():  # FFmpeg's complaints about a damaged file; the errors below name it
        cap = cv2.VideoCapture(str(path))
        try:
            if not cap.isOpened():
                raise ValueError(f"{path}: not a video OpenCV can open")
            fps = float(cap.get(cv2.CAP_PROP_FPS)) or None
            stated = cap.get(cv2.CAP_PROP_FRAME_COUNT)
            while index <= wanted[-1]:
                if not cap.grab():
                    break
                if index in keep:
                    ok, frame = cap.retrieve()
                    if not ok:
                        raise ValueError(f"{path}: frame {index} could not be decoded")
                    check_image_pixels(path, frame.shape[1], frame.shape[0])
                    images.append(cv2.cvtColor(frame, cv2.COLOR_BGR2RGB))
                index += 1
        finally:
            cap.release()
    if index == 0:
        raise ValueError(f"{path}: could not decode any frame (not a video OpenCV reads, or damaged)")
    if len(images) < len(wanted):
        raise _short(path, index, start, stride, frames)
    total = int(stated) if np.isfinite(stated) and int(stated) >= index else None
    return images, fps if fps is None or np.isfinite(fps) and fps > 0 else None, total
