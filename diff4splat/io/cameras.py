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

with fx, cx divided by the image width, fy, cy by the image height, two zeros (radial distortion) and the 3×4
world-to-camera matrix [R | t] row-major (OpenCV axes).
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
"""Upper bound of the bytes one frame takes in a camera file (an indented ``cameras.json`` frame is about 1 KB):
a larger file is refused before it is parsed."""

def _check_camera_file(path: str | os.PathLike, what: str) -> Path:
    """``path`` checked to be a regular file (:func:`check_input_file`) of at most ``frames`` limit ×
    :data:`CAMERA_FILE_BYTES_PER_FRAME` + 64 KB (else LimitError), before it is read."""
    path = check_input_file(path, what)
    size, frames = path.stat().st_size, limit("frames")
    bound = frames * CAMERA_FILE_BYTES_PER_FRAME + (1 << 16)
    if size > bound:
        raise LimitError(f"{path}: {size} bytes is too large for a camera path of at most {frames} frames "
                         f"(limit {bound} bytes; set {LIMITS['frames'].env} to raise it)")
    return path


def save_cameras_json(path: str | os.PathLike, camera_path: CameraPath) -> None:
    """Write ``camera_path`` as ``cameras.json`` (module docstring) atomically, as full-precision JSON numbers (float32
    round-trips exactly); ValueError if it fails :meth:`CameraPath.validate`."""
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
    """Read a ``cameras.json`` (module docstring; "times" optional, default i/(T−1), other keys ignored) as a validated
    float32 :class:`CameraPath` on the CPU, as stored.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ValueError: not a regular UTF-8 file of valid JSON, a missing key, a value of the wrong type or shape, or a
            field failing :meth:`CameraPath.validate` (each named); more frames than the ``frames`` limit, width ×
            height above ``image_pixels`` or a file too large for the ``frames`` limit (LimitError, before parsing).
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
            check_limit("frames", len(data[key]), f"{path}: a camera path of")
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
    """The frame lines of a RealEstate10K camera file (module docstring): integer timestamps (µs) and the 18 numbers
    after each, in file order (no frames: empty lists). An optional non-numeric first line and blank lines are skipped.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        ValueError: not a regular UTF-8 text file; naming the line: a wrong number of values, non-numeric values or
            non-zero distortion; more frames than the ``frames`` limit (LimitError, the file size checked first).
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
    check_limit("frames", len(rows), f"{path}: a camera path of")
    return stamps, rows


def load_realestate10k(path: str | os.PathLike, width: int, height: int, relative: bool = True) -> CameraPath:
    """Read a RealEstate10K camera file (:func:`read_realestate10k_lines`) as a validated float32 :class:`CameraPath`
    for ``width`` × ``height`` images: intrinsics fx·W, fy·H, cx·W, cy·H; times t_i = (ts_i − ts_0)/(ts_{T−1} − ts_0)
    (T = 1 → [0]); with ``relative``, poses re-expressed relative to the first camera (V_i V_0⁻¹).

    Raises:
        FileNotFoundError / ValueError: as :func:`read_realestate10k_lines`; no frames; decreasing timestamps; equal
            first and last timestamps with T > 1; a field failing :meth:`CameraPath.validate`.
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
    """Write ``camera_path`` (its own world frame) in the RealEstate10K format atomically, with ``url`` (one line) as
    the first line if given. Timestamps ts_i = round(t_i·(T−1)·10⁶/fps) µs place uniform times at i/fps; numbers
    have 9 significant digits (float32 exact).

    Raises:
        ValueError: naming ``url`` (a line break, or numeric), ``fps`` (not > 0 and finite) or a field of
            :meth:`CameraPath.validate`.
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
