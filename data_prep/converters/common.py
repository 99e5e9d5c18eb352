"""Helpers shared by every source converter: source-file reading with one-line errors, depth decoding, frame IO
and the atomic scene writer. Camera axes and pose conversions are in :mod:`data_prep.converters.camera_conventions`.
"""
from __future__ import annotations

import gzip
import json
import os
import pickle
import warnings
import zipfile
import zlib
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from diff4splat.cameras import CameraPath
from diff4splat.io.inputs import check_input_file, check_input_folder
from diff4splat.io.structured import read_json

from ..format import SceneWriter

__all__ = ["only_stem", "decode_scaled_uint16", "float16_bits_to_float", "disparity_to_depth", "finite_positive_or_inf",
           "read_rgb_uint8", "read_uint16_png", "check_downscale", "downscale_rgb", "downscaled_intrinsics",
           "iter_video_frames", "select_frames", "write_scene", "require_file", "require_dir", "load_npy", "load_npz",
           "load_number_rows", "load_json_file", "load_gzip_json"]


def require_file(path: str | os.PathLike, what: str) -> Path:
    """``Path(path)`` if it is a regular file (or a link to one). Raises FileNotFoundError: nothing is there, or a
    dangling link; ValueError: a folder, FIFO, socket, device or symlink loop, said as such
    (:func:`diff4splat.io.inputs.check_input_file`)."""
    p = Path(path)
    try:
        return check_input_file(p, what)
    except FileNotFoundError as e:
        if os.path.islink(p):
            raise
        raise FileNotFoundError(f"{what} not found: {p}") from e


def only_stem(folder: Path, pattern: str, option: str, what: str) -> str:
    """Stem of the single file matching ``pattern`` in ``folder`` (the default when ``option`` is not given). Raises
    FileNotFoundError: no ``folder``; ValueError: zero or several matches."""
    require_dir(folder, "source")
    found = sorted(folder.glob(pattern))
    if len(found) != 1:
        raise ValueError(f"{option} must be given: {folder} holds {len(found)} {what}")
    return found[0].stem


def require_dir(path: str | os.PathLike, what: str) -> Path:
    """``Path(path)`` if it is a folder (or a link to one). Raises FileNotFoundError: nothing is there, or a dangling
    link; ValueError: something else, said as such (:func:`diff4splat.io.inputs.check_input_folder`)."""
    p = Path(path)
    try:
        return check_input_folder(p, f"{what} folder")
    except FileNotFoundError as e:
        if os.path.islink(p):
            raise
        raise FileNotFoundError(f"{what} folder not found: {p}") from e


_NUMPY_READ_ERRORS = (EOFError, ValueError, zipfile.BadZipFile, pickle.UnpicklingError, zlib.error)
"""What ``np.load`` raises on a truncated, empty or foreign file (an ``OSError`` of the path is left to the CLI)."""


def _why(e: BaseException) -> str:
    """``np.load``'s complaint in the user's terms (numpy's pickle message suggests ``allow_pickle=``)."""
    if "allow_pickle" in str(e) or isinstance(e, pickle.UnpicklingError):
        return "it holds pickled Python objects, which are never loaded; arrays of numbers are expected"
    return str(e) or type(e).__name__


def load_npy(path: str | os.PathLike, what: str) -> np.ndarray:
    """The array of the ``.npy`` file ``path`` (never unpickled). Raises what :func:`require_file` raises, and
    ValueError: empty, truncated, not ``.npy`` or a ``.npz`` archive."""
    p = require_file(path, what)
    try:
        arr = np.load(p, allow_pickle=False)
    except _NUMPY_READ_ERRORS as e:
        raise ValueError(f"{what}: {p} is not a readable .npy array ({_why(e)})") from None
    if not isinstance(arr, np.ndarray):
        arr.close()
        raise ValueError(f"{what}: {p} is a .npz archive, not a .npy array")
    return arr


def load_npz(path: str | os.PathLike, what: str, required: Iterable[str],
             optional: Iterable[str] = ()) -> dict[str, np.ndarray]:
    """The ``required`` arrays and those of ``optional`` present in the ``.npz`` archive ``path`` (never unpickled).
    Raises what :func:`require_file` raises, and ValueError: empty, truncated or not a ``.npz`` archive, a missing
    required array, or an unreadable one (corrupt member, pickled objects), each naming the file."""
    p = require_file(path, what)
    try:
        z = np.load(p, allow_pickle=False)
    except _NUMPY_READ_ERRORS as e:
        raise ValueError(f"{what}: {p} is not a readable .npz archive ({_why(e)})") from None
    if not isinstance(z, np.lib.npyio.NpzFile):
        raise ValueError(f"{what}: {p} is a .npy array, not a .npz archive")
    required = list(required)
    with z:
        missing = [k for k in required if k not in z.files]
        if missing:
            raise ValueError(f"{what}: {p} misses {missing} (it holds {z.files})")
        out = {}
        for k in [*required, *(k for k in optional if k in z.files and k not in required)]:
            try:
                out[k] = np.asarray(z[k])
            except _NUMPY_READ_ERRORS as e:
                raise ValueError(f"{what}: {p}: {k!r} is not a readable array ({_why(e)})") from None
    return out


def load_number_rows(path: str | os.PathLike, what: str, ncols: int, columns: str = "") -> np.ndarray:
    """The (N, ``ncols``) float64 rows of a whitespace-separated text file of numbers (``#`` comments allowed). Raises
    what :func:`require_file` raises, and ValueError: an empty file, a line that is not numbers, or rows of another
    width than ``ncols`` (``columns`` names them), each naming the file."""
    p = require_file(path, what)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # numpy's "input contained no data": said below
            rows = np.loadtxt(p, ndmin=2, dtype=np.float64)
    except (ValueError, UnicodeDecodeError) as e:
        raise ValueError(f"{p}: {e}") from None
    if rows.size == 0:
        raise ValueError(f"{p}: no lines of numbers (an empty file)")
    if rows.shape[1] != ncols:
        raise ValueError(f"{p}: expected {ncols} values per line{f' ({columns})' if columns else ''}, "
                         f"got {rows.shape[1]}")
    return rows


def load_json_file(path: str | os.PathLike, what: str, expect: type | None = dict) -> Any:
    """:func:`diff4splat.io.structured.read_json` (empty, truncated, non-UTF-8 or non-JSON files named)."""
    return read_json(require_file(path, what), what, expect)


def load_gzip_json(path: str | os.PathLike, what: str, expect: type | None = None) -> Any:
    """The JSON value of a gzip-compressed file (``.jgz``). Raises what :func:`require_file` raises, and ValueError: not
    gzip, truncated, not UTF-8 or not JSON, or a top-level value that is not an ``expect``, each naming the file."""
    p = require_file(path, what)
    try:
        with gzip.open(p, "rt", encoding="utf8") as f:
            data = json.load(f)
    except json.JSONDecodeError as e:
        raise ValueError(f"{what}: {p} is not valid JSON ({e.msg} at line {e.lineno} column {e.colno})") from None
    except (gzip.BadGzipFile, EOFError, zlib.error, UnicodeDecodeError) as e:
        raise ValueError(f"{what}: {p} is not gzip-compressed JSON ({_why(e)})") from None
    if expect is not None and not isinstance(data, expect):
        raise ValueError(f"{what}: {p} must hold a JSON {'object' if expect is dict else expect.__name__}, "
                         f"got {type(data).__name__}")
    return data


def finite_positive_or_inf(depth: np.ndarray) -> np.ndarray:
    """float32 depth with every non-finite or ≤ 0 value replaced by +inf (the format's invalid value)."""
    d = np.asarray(depth, dtype=np.float32)
    return np.where(np.isfinite(d) & (d > 0), d, np.float32(np.inf)).astype(np.float32)


def decode_scaled_uint16(raw: np.ndarray, metres_per_unit: float, invalid: tuple[int, ...] = (0,)) -> np.ndarray:
    """uint16 depth image → float32 metres: raw·``metres_per_unit``; the ``invalid`` codes → +inf. Raises ValueError:
    ``raw`` is not an unsigned 16-bit image."""
    raw = np.asarray(raw)
    if raw.dtype != np.uint16:
        raise ValueError(f"expected a 16-bit depth image, got dtype {raw.dtype}")
    d = raw.astype(np.float64) * metres_per_unit
    bad = np.isin(raw, np.asarray(invalid, dtype=np.uint16))
    return finite_positive_or_inf(np.where(bad, np.inf, d))


def float16_bits_to_float(raw: np.ndarray) -> np.ndarray:
    """Reinterpret the bits of a uint16 image as float16, widened to float32: CO3D's / Dynamic Replica's 16-bit PNG
    depth (dynamic_stereo ``_load_16big_png_depth``). Raises ValueError: ``raw`` is not uint16."""
    raw = np.ascontiguousarray(raw)
    if raw.dtype != np.uint16:
        raise ValueError(f"expected a 16-bit image, got dtype {raw.dtype}")
    return raw.view(np.float16).astype(np.float32)


def disparity_to_depth(disparity: np.ndarray, fx: float, baseline: float) -> np.ndarray:
    """Rectified-stereo disparity (H, W), pixels → z-depth, metres: z = fx·B / d (``fx`` pixels, ``baseline`` B
    metres); d ≤ 0 or non-finite → +inf."""
    d = np.asarray(disparity, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = fx * baseline / d
    return finite_positive_or_inf(np.where(np.isfinite(d) & (d > 0), z, np.inf))


def read_rgb_uint8(path: str | os.PathLike) -> np.ndarray:
    """Decode an 8- or 16-bit (scaled by 255/65535, rounded) colour image file to (H, W, 3) uint8 RGB, alpha dropped.
    Raises FileNotFoundError: missing file; ValueError: OpenCV cannot decode it."""
    p = require_file(path, "image")
    img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f"could not decode {p} as an image")
    if img.dtype == np.uint16:
        img = np.round(img.astype(np.float64) * (255.0 / 65535.0)).astype(np.uint8)
    if img.dtype != np.uint8:
        raise ValueError(f"{p}: expected an 8- or 16-bit image, got {img.dtype}")
    if img.ndim == 2:
        return np.repeat(img[..., None], 3, axis=-1)
    code = cv2.COLOR_BGRA2RGB if img.shape[2] == 4 else cv2.COLOR_BGR2RGB
    return cv2.cvtColor(img, code)


def read_uint16_png(path: str | os.PathLike) -> np.ndarray:
    """Read a single-channel 16-bit PNG unchanged as (H, W) uint16. Raises FileNotFoundError: missing file; ValueError:
    undecodable, or not single-channel 16-bit."""
    p = require_file(path, "depth image")
    img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    if img is None or img.dtype != np.uint16 or img.ndim != 2:
        got = None if img is None else (img.dtype, img.shape)
        raise ValueError(f"{p} must be a single-channel 16-bit PNG, got {got}")
    return img


def check_downscale(factor, width: int, height: int) -> int:
    """``factor`` if it is an int in [1, min(width, height)], else ValueError naming ``downscale``."""
    if isinstance(factor, bool) or not isinstance(factor, int) or not 1 <= factor <= min(width, height):
        raise ValueError(f"downscale must be an int in [1, {min(width, height)}] for {width}×{height} images, "
                         f"got {factor!r}")
    return factor


def downscale_rgb(rgb: np.ndarray, factor: int) -> np.ndarray:
    """(H, W, 3) uint8 → (H // factor, W // factor, 3) uint8 by ``cv2.INTER_AREA`` (factor 1: ``rgb`` itself)."""
    if factor == 1:
        return rgb
    h, w = rgb.shape[:2]
    return cv2.resize(rgb, (w // factor, h // factor), interpolation=cv2.INTER_AREA)


def downscaled_intrinsics(K: np.ndarray, width: int, height: int, factor: int) -> tuple[np.ndarray, int, int]:
    """(K', W // factor, H // factor): pixel intrinsics (..., 3, 3) of ``width``×``height`` images resized by
    :func:`downscale_rgb`; fx, cx scale by (W // f) / W and fy, cy by (H // f) / H."""
    w2, h2 = width // factor, height // factor
    K2 = np.array(K, dtype=np.float64)
    K2[..., 0, :] *= w2 / width
    K2[..., 1, :] *= h2 / height
    return K2, w2, h2


def iter_video_frames(path: str | os.PathLike, indices: list[int]) -> Iterator[np.ndarray]:
    """Stream the frames ``indices`` (increasing) of a video file as (H, W, 3) uint8 RGB, decoding sequentially so
    memory holds one frame. Raises FileNotFoundError: missing file; ValueError: unreadable video, or fewer frames than
    ``max(indices) + 1``."""
    p = require_file(path, "video")
    cap = cv2.VideoCapture(str(p))
    if not cap.isOpened():
        raise ValueError(f"could not open video {p}")
    try:
        wanted = iter(indices)
        target = next(wanted, None)
        frame_index = 0
        while target is not None:
            ok, frame = cap.read()
            if not ok:
                raise ValueError(f"{p} has only {frame_index} frames, frame {target} was requested")
            if frame_index == target:
                yield cv2.cvtColor(frame, cv2.COLOR_BGR2RGB)
                target = next(wanted, None)
            frame_index += 1
    finally:
        cap.release()


def select_frames(total: int, start: int = 0, stride: int = 1, max_frames: int | None = None, *,
                  source: str | os.PathLike | None = None) -> list[int]:
    """Source frame indices start, start+stride, … (< total), at most ``max_frames`` of them; ``source``: where the
    frames were counted, named when there are none. Raises ValueError: ``total`` < 1, ``start`` outside [0, total),
    ``stride`` < 1, ``max_frames`` < 1."""
    if total < 1:
        raise ValueError(f"{'the source sequence' if source is None else source} has no frames")
    if not isinstance(start, int) or not 0 <= start < total:
        raise ValueError(f"start must be an int in [0, {total}), got {start!r}")
    if not isinstance(stride, int) or stride < 1:
        raise ValueError(f"stride must be an int ≥ 1, got {stride!r}")
    if max_frames is not None and (not isinstance(max_frames, int) or max_frames < 1):
        raise ValueError(f"max_frames must be an int ≥ 1 or None, got {max_frames!r}")
    idx = list(range(start, total, stride))
    return idx[:max_frames] if max_frames is not None else idx


FrameSource = Callable[[str], Iterable[tuple[np.ndarray, np.ndarray | None]]]
"""camera name → its T frames in order, each (rgb (H, W, 3) uint8, depth (H, W) float32 metres or None)."""


def write_scene(out: str | os.PathLike, *, source: str, dynamic: bool, depth_source: str, fps: float,
                cameras: dict[str, CameraPath], timestamps: np.ndarray, frames: FrameSource,
                tracks: tuple[np.ndarray, np.ndarray] | None = None, depth_scale: float = 1.0,
                depth_shift: float = 0.0, extra: dict | None = None, replace: bool = False) -> Path:
    """Write one converted scene folder ``out`` with :class:`data_prep.format.SceneWriter` (atomic, validated).
    ``source`` … ``extra``: meta fields (FORMAT.md); ``cameras``: name → T-frame path, reference first; ``timestamps``:
    (T,) seconds shared by every camera; ``frames(name)`` yields a camera's T (rgb, depth) pairs; ``tracks``: optional
    (points (P, T, 3) metres, visibility (P, T) bool). Returns ``out``. Raises ValueError: a camera yields a number of
    frames other than T, or any SceneWriter/validator error (bad shapes, invalid depth values, unsynchronised cameras);
    FileExistsError: ``out`` exists and ``replace`` is false."""
    T = len(timestamps)
    with SceneWriter(out, source=source, dynamic=dynamic, depth_source=depth_source, num_frames=T,
                     fps=float(fps), depth_scale=float(depth_scale), depth_shift=float(depth_shift),
                     extra=extra, replace=replace, replace_flag="--replace") as w:
        for name, path in cameras.items():
            w.add_camera(name, path, timestamps)
        for name in cameras:
            n = 0
            for i, (rgb, depth) in enumerate(frames(name)):
                if i >= T:
                    raise ValueError(f"camera {name!r} yields more than num_frames={T} frames")
                w.write_frame(name, i, rgb, depth)
                n += 1
            if n != T:
                raise ValueError(f"camera {name!r} yields {n} frames, expected {T}")
        if tracks is not None:
            w.write_tracks(*tracks)
    return Path(out)
