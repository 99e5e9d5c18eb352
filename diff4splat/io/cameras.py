"""Camera path files: diff4splat's ``cameras.json`` and the RealEstate10K text format.

``cameras.json`` (also written to generate's output folder)::

    {
      "width": 64, "height": 48,                  # image size, pixels
      "Ks": [[[fx, 0, cx], [0, fy, cy], [0, 0, 1]], ...],   # T × 3 × 3, pixels
      "viewmats": [[[r11, r12, r13, t1], ..., [0, 0, 0, 1]], ...],  # T × 4 × 4 world-to-camera, OpenCV
      "times": [0.0, ..., 1.0]                    # T, clip times in [0, 1] (optional on load)
    }

RealEstate10K (Zhou et al., "Stereo Magnification", SIGGRAPH 2018; dataset README): an optional
first line with the video URL, then one line per frame::

    timestamp_us fx fy cx cy 0 0 r11 r12 r13 t1 r21 r22 r23 t2 r31 r32 r33 t3

with fx, cx divided by the image width, fy, cy divided by the image height, the two zeros
(radial distortion, always zero in the dataset) and the 3×4 world-to-camera matrix [R | t] row-major
(OpenCV axes).
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import torch

from diff4splat.cameras.path import CameraPath
from diff4splat.io.atomic import atomic_output_path
from diff4splat.io.inputs import check_input_file
from diff4splat.io.structured import read_json, read_text
from diff4splat.utils.checks import check_positive, check_positive_int
from diff4splat.utils.limits import LIMITS, LimitError, check_limit, limit

__all__ = ["save_cameras_json", "load_cameras_json", "load_realestate10k", "read_realestate10k_lines",
           "save_realestate10k", "CAMERA_FILE_BYTES_PER_FRAME"]

CAMERA_FILE_BYTES_PER_FRAME = 4096
"""Generous upper bound of the bytes one frame takes in a camera file (an indented ``cameras.json``
frame is about 1 KB, a RealEstate10K line about 200 bytes): a larger file is refused before it is parsed."""


def _check_camera_file(path: str | os.PathLike, what: str) -> Path:
    """Check ``path`` is a regular file no larger than the ``frames`` limit allows, before it is read.

    Raises:
        FileNotFoundError / ValueError: :func:`diff4splat.io.inputs.check_input_file`.
        LimitError: the file is larger than ``frames`` limit × :data:`CAMERA_FILE_BYTES_PER_FRAME` (+ 64 KB).
    """
    path = check_input_file(path, what)
    size, frames = path.stat().st_size, limit("frames")
    bound = frames * CAMERA_FILE_BYTES_PER_FRAME + (1 << 16)
    if size > bound:
        raise LimitError(f"{path}: {size} bytes is too large for a camera path of at most {frames} frames "
                         f"(limit {bound} bytes; set {LIMITS['frames'].env} to raise it)")
    return path


def _check_frame_count(path: Path, count: int) -> None:
    check_limit("frames", count, f"{path}: a camera path of")


def save_cameras_json(path: str | os.PathLike, camera_path: CameraPath) -> None:
    """Write a camera path as ``cameras.json`` (module docstring), atomically.

    Values are written as JSON numbers with full double precision, so float32 paths round-trip
    exactly.

    Args:
        path: output file.
        camera_path: validated :class:`CameraPath` (T cameras).

    Raises:
        ValueError: ``camera_path`` fails :meth:`CameraPath.validate`.
    """
    camera_path.validate()
    data = {
        "width": camera_path.width,
        "height": camera_path.height,
        "Ks": camera_path.Ks.detach().cpu().double().tolist(),
        "viewmats": camera_path.viewmats.detach().cpu().double().tolist(),
        "times": camera_path.times.detach().cpu().double().tolist(),
    }
    with atomic_output_path(path) as tmp:
        with open(tmp, "w", encoding="utf-8") as f:
            json.dump(data, f, indent=1)
            f.write("\n")


def _tensor(data: dict, key: str, shape_tail: tuple[int, ...], path: Path) -> torch.Tensor:
    try:
        t = torch.tensor(data[key], dtype=torch.float32, device="cpu")  # files load onto the CPU
    except (TypeError, ValueError) as e:
        raise ValueError(f"{path}: '{key}' must be a nested list of numbers of shape "
                         f"(T, {', '.join(map(str, shape_tail))}): {e}") from None
    if t.dim() != 1 + len(shape_tail) or tuple(t.shape[1:]) != shape_tail:
        raise ValueError(f"{path}: '{key}' must have shape (T, {', '.join(map(str, shape_tail))}), "
                         f"got {tuple(t.shape)}")
    return t


def load_cameras_json(path: str | os.PathLike) -> CameraPath:
    """Read a ``cameras.json`` camera path (module docstring).

    Args:
        path: JSON file with keys "width", "height", "Ks", "viewmats" and optionally "times"
            (default t_i = i/(T−1)); other keys are ignored.

    Returns:
        Validated float32 :class:`CameraPath`, as stored (not re-expressed relative to the first
        camera).

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ValueError: ``path`` is not a regular file; not UTF-8 text, invalid JSON, a missing key (named), a
            value of the wrong type or shape, or a field failing :meth:`CameraPath.validate` (named);
            more frames than the ``frames`` limit or width × height above the ``image_pixels`` limit
            (:class:`diff4splat.utils.limits.LimitError`, checked before any tensor is built; the file size
            is checked before it is parsed).
    """
    path = _check_camera_file(path, "camera file")
    data = read_json(path, "camera file")
    for key in ("width", "height", "Ks", "viewmats"):
        if key not in data:
            raise ValueError(f"{path}: missing key '{key}'")
    for key in ("width", "height"):
        try:
            check_positive_int(f"'{key}'", data[key], "pixels")
        except ValueError as e:
            raise ValueError(f"{path}: {e}") from None
    check_limit("image_pixels", data["width"] * data["height"],
                f"{path}: width × height = {data['width']}×{data['height']} =")
    for key in ("viewmats", "Ks"):
        if isinstance(data[key], list):
            _check_frame_count(path, len(data[key]))
    viewmats = _tensor(data, "viewmats", (4, 4), path)
    Ks = _tensor(data, "Ks", (3, 3), path)
    times = None
    if data.get("times") is not None:
        try:
            times = torch.tensor(data["times"], dtype=torch.float32, device="cpu")
        except (TypeError, ValueError) as e:
            raise ValueError(f"{path}: 'times' must be a list of numbers: {e}") from None
    try:
        return CameraPath(viewmats, Ks, data["width"], data["height"], times)
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from None


def read_realestate10k_lines(path: str | os.PathLike) -> tuple[list[int], list[list[float]]]:
    """The frame lines of a RealEstate10K camera file (module docstring): integer timestamps (µs) and the 18
    numbers after each, in file order; no frames is an empty list (the caller names what that means).

    :func:`load_realestate10k` reads through this; a converter that needs the timestamps before it knows the
    image size (``data_prep``'s RealEstate10K converter) too, so both hold a file to the same rules.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ValueError: ``path`` is not a regular UTF-8 text file; naming the line for a wrong number of values,
            non-numeric values or non-zero distortion; more frames than the ``frames`` limit
            (:class:`diff4splat.utils.limits.LimitError`; the file size is checked before it is read).
    """
    path = _check_camera_file(path, "RealEstate10K camera file")
    text = read_text(path, "RealEstate10K camera file")
    rows, stamps = [], []
    for lineno, line in enumerate(text.splitlines(), start=1):
        words = line.split()
        if not words:
            continue
        if lineno == 1 and not _is_number(words[0]):
            continue  # URL line
        if len(words) != 19:
            raise ValueError(f"{path}:{lineno}: expected 19 values per frame, got {len(words)}")
        try:
            stamp = int(words[0])
            vals = [float(w) for w in words[1:]]
        except ValueError:
            raise ValueError(f"{path}:{lineno}: values must be numbers (an integer timestamp first)") from None
        if vals[4] != 0.0 or vals[5] != 0.0:
            raise ValueError(f"{path}:{lineno}: non-zero distortion ({vals[4]}, {vals[5]}) is not supported")
        stamps.append(stamp)
        rows.append(vals)
    _check_frame_count(path, len(rows))
    return stamps, rows


def load_realestate10k(path: str | os.PathLike, width: int, height: int, relative: bool = True) -> CameraPath:
    """Read a RealEstate10K camera file (module docstring) for images of ``width`` × ``height``.

    Intrinsics are de-normalised: fx·W, fy·H, cx·W, cy·H. Times are the timestamps mapped linearly
    to [0, 1]: t_i = (ts_i − ts_0)/(ts_{T−1} − ts_0) (T = 1 → [0]).

    Args:
        path: text file; an optional first line that is not numeric (the YouTube URL), blank lines
            ignored, then 19 numbers per frame.
        width: image width W, pixels.
        height: image height H, pixels.
        relative: re-express the poses relative to the first camera (V_i V_0⁻¹, first = I), the
            docs/DESIGN.md convention; ``False`` keeps the dataset's world frame.

    Returns:
        Validated float32 :class:`CameraPath`.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ValueError: ``path`` is not a regular UTF-8 text file; naming the line for a wrong number of
            values, non-numeric values or non-zero distortion; no frames; decreasing timestamps; equal
            first and last timestamps with T > 1; a field failing :meth:`CameraPath.validate`
            (``width``/``height`` included); more frames than the ``frames`` limit
            (:class:`diff4splat.utils.limits.LimitError`; the file size is checked before it is parsed).
    """
    stamps, rows = read_realestate10k_lines(path)
    if not rows:
        raise ValueError(f"{path}: no camera lines")
    width, height = check_positive_int("width", width, "pixels"), check_positive_int("height", height, "pixels")
    vals = torch.tensor(rows, dtype=torch.float64, device="cpu")  # (T, 18); files load onto the CPU
    T = vals.shape[0]
    Ks = torch.zeros(T, 3, 3, dtype=torch.float64, device="cpu")
    Ks[:, 0, 0], Ks[:, 1, 1] = vals[:, 0] * width, vals[:, 1] * height
    Ks[:, 0, 2], Ks[:, 1, 2], Ks[:, 2, 2] = vals[:, 2] * width, vals[:, 3] * height, 1.0
    viewmats = torch.eye(4, dtype=torch.float64, device="cpu").repeat(T, 1, 1)
    viewmats[:, :3, :] = vals[:, 6:].reshape(T, 3, 4)
    ts = torch.tensor(stamps, dtype=torch.float64, device="cpu")
    if T > 1 and bool((ts[1:] < ts[:-1]).any()):
        raise ValueError(f"{path}: timestamps must be non-decreasing")
    if T > 1 and ts[-1] == ts[0]:
        raise ValueError(f"{path}: first and last timestamps are equal; times cannot be normalised")
    times = (ts - ts[0]) / (ts[-1] - ts[0]) if T > 1 else torch.zeros(1, dtype=torch.float64, device="cpu")
    try:
        cam = CameraPath(viewmats, Ks, width, height, times)
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from None
    if relative:
        cam = cam.relative_to_first()
    return cam.to(torch.float32)


def save_realestate10k(
    path: str | os.PathLike, camera_path: CameraPath, url: str | None = None, fps: float = 30
) -> None:
    """Write a camera path in the RealEstate10K text format (module docstring), atomically.

    Timestamps (integer microseconds) place the clip over (T−1)/fps seconds:
    ts_i = round(t_i·(T−1)·10⁶/fps), so uniform times give frame i at i/fps and reading the file
    back recovers t_i (to 1 µs). Numbers are written with 9 significant digits (float32 exact).

    Args:
        path: output text file.
        camera_path: validated :class:`CameraPath`; its own world frame is written as is.
        url: optional first line (e.g. the source video URL); must be one line.
        fps: frames per second of the clip, > 0.

    Raises:
        ValueError: naming ``url`` (contains a line break or is numeric, which would be read as a
            frame), ``fps`` (not positive and finite) or a field of :meth:`CameraPath.validate`.
    """
    camera_path.validate()
    fps = check_positive("fps", fps)
    if url is not None and ("\n" in url or "\r" in url or not url.strip() or _is_number(url.split()[0])):
        raise ValueError(f"url must be a single non-numeric line, got {url!r}")
    W, H, T = camera_path.width, camera_path.height, len(camera_path)
    K = camera_path.Ks.detach().cpu().double()
    V = camera_path.viewmats.detach().cpu().double()
    t = camera_path.times.detach().cpu().double()
    stamps = torch.round(t * (T - 1) * 1e6 / fps).long().tolist()
    lines = [url.strip()] if url is not None else []
    for i in range(T):
        intr = [K[i, 0, 0] / W, K[i, 1, 1] / H, K[i, 0, 2] / W, K[i, 1, 2] / H, 0.0, 0.0]
        nums = [float(x) for x in intr] + V[i, :3, :].reshape(-1).tolist()
        lines.append(" ".join([str(stamps[i])] + [f"{x:.9g}" for x in nums]))
    with atomic_output_path(path) as tmp:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write("\n".join(lines) + "\n")


def _is_number(word: str) -> bool:
    try:
        float(word)
    except ValueError:
        return False
    return True
