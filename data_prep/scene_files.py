"""What a scene folder holds, file by file (``data_prep/FORMAT.md``): its file and folder names, the format's
constants, ``meta.json`` (:class:`SceneMeta`) and the readers of single files. The lowest module of the format
(below :mod:`data_prep.validate` and :mod:`data_prep.format`, which re-exports it).
"""
from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from diff4splat.io.image import read_image
from diff4splat.io.structured import read_json
from diff4splat.utils.checks import check_int, check_number, is_int, is_number
from diff4splat.utils.errors import parse_naming

__all__ = ["META_FILE", "CAMERAS_FILE", "CAPTION_FILE", "TRACKS_FILE", "OBJECTS_FILE", "NO_SURFACE",
           "RGB_DIR", "RGB_SUFFIX", "DEPTH_DIR",
           "DEPTH_SUFFIX", "FORMAT_VERSION", "DEPTH_SOURCES", "SYNC_TOLERANCE_S", "TIMES_TOLERANCE", "SceneMeta",
           "list_scenes", "is_scene", "frame_name", "check_camera_name", "read_rgb", "read_timestamps",
           "timestamps_to_times", "size_problem", "depth_values_problem", "objects_problem"]

META_FILE = "meta.json"
"""A scene's description (:class:`SceneMeta`); a folder holding one is a scene (:func:`is_scene`)."""
CAMERAS_FILE = "cameras.json"
"""A camera folder's path: diff4splat's ``cameras.json`` plus ``"timestamps"`` (T,) seconds."""
CAPTION_FILE = "caption.txt"
"""A scene's optional caption: one non-empty UTF-8 line."""
TRACKS_FILE = "tracks.npz"
"""A scene's optional 3D point tracks: ``points`` (P, T, 3) float32 metres, ``visibility`` (P, T) bool."""
OBJECTS_FILE = "objects.npz"
"""A scene's optional object motion: ``poses`` (O, T, 3, 4) float64 affine world maps [A | b] of each object at each
frame, and per camera ``ids_<camera>`` (T, H, W) uint8 id maps (0 background, k + 1 object k, :data:`NO_SURFACE`)."""
NO_SURFACE = 255
"""Id of a pixel with no surface (depth +inf) in an ``objects.npz`` id map."""
RGB_DIR = "rgb"
"""A camera folder's sub-folder of RGB frames, ``frame_name(i, RGB_SUFFIX)``: 8-bit RGB PNG."""
RGB_SUFFIX = ".png"
DEPTH_DIR = "depth"
"""A camera folder's sub-folder of depth frames, ``frame_name(i, DEPTH_SUFFIX)``: float32 EXR channel "Z", metres."""
DEPTH_SUFFIX = ".exr"

FORMAT_VERSION = 1
"""Version of ``data_prep/FORMAT.md`` written by this module."""
DEPTH_SOURCES: tuple[str, ...] = ("ground_truth", "aligned_estimate", "none")
"""Allowed values of ``meta["depth_source"]``."""
SYNC_TOLERANCE_S = 1e-3
"""Cameras are synchronised when their timestamps agree within this many seconds."""
TIMES_TOLERANCE = 1e-4
"""``times`` must equal the normalised ``timestamps`` within this (times are in [0, 1])."""

_CAMERA_NAME = re.compile(r"^[A-Za-z0-9_-][A-Za-z0-9_.-]*$")


def check_camera_name(name: Any) -> str:
    """Return ``name`` if it is a valid camera folder name ([A-Za-z0-9_.-]+, no leading '.'), else ValueError."""
    if not isinstance(name, str) or not _CAMERA_NAME.match(name):
        raise ValueError(f"cameras: {name!r} is not a valid camera folder name ([A-Za-z0-9_.-]+, no leading '.')")
    return name


def frame_name(index: int, suffix: str) -> str:
    """File name of frame ``index``: ``f"{index:05d}{suffix}"`` (e.g. ``00017.png``)."""
    return f"{index:05d}{suffix}"


@dataclass
class SceneMeta:
    """The typed content of ``meta.json``; each field is specified in FORMAT.md ("meta.json"). ``extra`` holds any
    other JSON-serialisable keys. Raises ValueError naming the field and the value, on construction."""

    source: str
    dynamic: bool
    depth_source: str
    num_frames: int
    cameras: list[str]
    fps: float
    depth_scale: float = 1.0
    depth_shift: float = 0.0
    format_version: int = FORMAT_VERSION
    extra: dict[str, Any] = field(default_factory=dict)

    _KEYS = ("format_version", "source", "dynamic", "depth_source", "depth_scale", "depth_shift",
             "num_frames", "cameras", "fps")

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """Check every field (FORMAT.md table); numpy scalars become Python numbers. Raises ValueError naming it."""
        if not is_int(self.format_version) or self.format_version != FORMAT_VERSION:
            raise ValueError(f"format_version must be {FORMAT_VERSION}, got {self.format_version!r}")
        self.format_version = FORMAT_VERSION
        if not isinstance(self.source, str) or not self.source.strip():
            raise ValueError(f"source must be a non-empty string, got {self.source!r}")
        if not isinstance(self.dynamic, bool):
            raise ValueError(f"dynamic must be true or false, got {self.dynamic!r}")
        if self.depth_source not in DEPTH_SOURCES:
            raise ValueError(f"depth_source must be one of {list(DEPTH_SOURCES)}, got {self.depth_source!r}")
        self.depth_scale = check_number("depth_scale", self.depth_scale, lo=0, lo_open=True)
        self.depth_shift = check_number("depth_shift", self.depth_shift, what="metres")
        self.num_frames = check_int("num_frames", self.num_frames, 1)
        self.fps = check_number("fps", self.fps, lo=0, lo_open=True)
        if not isinstance(self.cameras, list) or not self.cameras:
            raise ValueError(f"cameras must be a non-empty list of camera folder names, got {self.cameras!r}")
        for name in self.cameras:
            check_camera_name(name)
        if len(set(self.cameras)) != len(self.cameras):
            raise ValueError(f"cameras must be unique, got {self.cameras}")
        if not isinstance(self.extra, dict) or any(k in self._KEYS for k in self.extra):
            raise ValueError("extra must be a dict whose keys are not standard meta keys")

    def to_dict(self) -> dict[str, Any]:
        """The JSON object of ``meta.json`` (standard keys first, then ``extra``)."""
        out = {k: getattr(self, k) for k in self._KEYS}
        out["cameras"] = list(self.cameras)
        out.update(self.extra)
        return out

    @classmethod
    def from_dict(cls, data: Any) -> SceneMeta:
        """Parse a ``meta.json`` object. Raises ValueError: not an object, a missing key or an invalid field."""
        if not isinstance(data, dict):
            raise ValueError(f"meta must be a JSON object, got {type(data).__name__}")
        missing = [k for k in cls._KEYS if k not in data]
        if missing:
            raise ValueError(f"missing key(s) {missing}")
        extra = {k: v for k, v in data.items() if k not in cls._KEYS}
        return cls(**{k: data[k] for k in cls._KEYS}, extra=extra)

    @classmethod
    def load(cls, path: str | os.PathLike) -> SceneMeta:
        """Read and parse ``meta.json``. Raises FileNotFoundError, or ValueError (invalid JSON or field) naming it."""
        return parse_naming(path, cls.from_dict, read_json(path, "scene meta", expect=None))


def timestamps_to_times(timestamps: np.ndarray) -> np.ndarray:
    """Clip times t_i = (ts_i − ts_0)/(ts_{T−1} − ts_0), float64 (T,) in [0, 1], of timestamps (T,) seconds; all
    zeros when the first and last timestamps are equal."""
    ts = np.asarray(timestamps, dtype=np.float64)
    span = ts[-1] - ts[0] if ts.size else 0.0
    return (ts - ts[0]) / span if span > 0 else np.zeros_like(ts)


def read_timestamps(path: str | os.PathLike) -> np.ndarray:
    """The ``"timestamps"`` (T,) float64 seconds of a scene camera's ``cameras.json``. Raises FileNotFoundError:
    ``path`` does not exist; ValueError: invalid JSON, missing ``timestamps``, not a list of finite numbers, or
    decreasing."""
    path = Path(path)
    data = read_json(path, "camera file", expect=None)
    ts = data.get("timestamps") if isinstance(data, dict) else None
    if not isinstance(ts, list) or not all(is_number(x) for x in ts):
        raise ValueError(f"{path}: 'timestamps' must be a list of finite numbers (seconds), got {str(ts)[:60]}")
    ts = np.asarray(ts, dtype=np.float64)
    if ts.size > 1 and bool((np.diff(ts) < 0).any()):
        raise ValueError(f"{path}: 'timestamps' must be non-decreasing")
    return ts


def read_rgb(path: str | os.PathLike) -> np.ndarray:
    """Decode an 8-bit RGB image file (:func:`diff4splat.io.image.read_image`) to (H, W, 3) float32 in [0, 1]. Raises
    FileNotFoundError: nothing exists at ``path``; ValueError: not a regular file, undecodable, over the
    ``image_pixels`` limit (:class:`diff4splat.utils.limits.LimitError`), or not 8-bit with exactly 3 channels."""
    img = read_image(path)
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
        ch = img.shape[2] if img.ndim == 3 else 1
        raise ValueError(f"{path} must be 8-bit RGB (3 channels), got dtype {img.dtype} with {ch} channel(s)")
    return img.astype(np.float32) / 255.0


def list_scenes(root: str | os.PathLike) -> list[Path]:
    """Scene folders of a dataset root: sorted non-hidden sub-folders holding ``meta.json``. Raises FileNotFoundError:
    ``root`` is not a folder."""
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"dataset folder not found: {root}")
    return sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".") and is_scene(p))


def is_scene(folder: str | os.PathLike) -> bool:
    """True when ``folder`` holds a :data:`META_FILE` (file or link to one): a complete scene (writes are atomic)."""
    return (Path(folder) / META_FILE).is_file()


def size_problem(kind: str, shape: tuple[int, ...], size: tuple[int, int]) -> str | None:
    """Why a ``kind`` ("image", "depth") frame of ``shape`` (H, W, …) does not fit its camera's (H, W), or None."""
    if tuple(shape[:2]) == tuple(size):
        return None
    return f"{kind} is {shape[1]}×{shape[0]}, {CAMERAS_FILE} says {size[1]}×{size[0]}"


def depth_values_problem(z: np.ndarray) -> str | None:
    """Why a depth map (H, W) breaks FORMAT.md (metres > 0, +inf where invalid): counts of NaN, −inf, ≤ 0; or None."""
    nan, neginf, nonpos = int(np.isnan(z).sum()), int(np.isneginf(z).sum()), int((z <= 0).sum())
    if not (nan or neginf or nonpos):
        return None
    return f"depth must be > 0 metres or +inf (invalid): {nan} NaN, {neginf} -inf, {nonpos} ≤ 0 value(s)"


def objects_problem(arrays: dict[str, np.ndarray], cameras: list[str], sizes: dict[str, tuple[int, int]],
                    num_frames: int, dynamic: bool) -> str | None:
    """Why the arrays of an ``objects.npz`` break FORMAT.md (``poses`` (O, T, 3, 4) float64 finite and invertible,
    static in a static scene; ``ids_<camera>`` (T, H, W) uint8 ≤ O or :data:`NO_SURFACE` for each of ``cameras``
    at its ``sizes`` (H, W)), or None."""
    poses = arrays.get("poses")
    if poses is None or poses.dtype != np.float64 or poses.ndim != 4 or poses.shape[1:] != (num_frames, 3, 4):
        got = "none" if poses is None else f"{poses.dtype} {poses.shape}"
        return f"'poses' must be float64 (O, {num_frames}, 3, 4), got {got}"
    if not np.isfinite(poses).all():
        return f"'poses' has {int((~np.isfinite(poses)).sum())} non-finite value(s)"
    if len(poses) and np.abs(np.linalg.det(poses[..., :3])).min() < 1e-12:
        return "'poses' has a singular map A (every A must be invertible)"
    if not dynamic and len(poses) and np.abs(poses - poses[:, :1]).max() > 1e-9:
        return "object poses change over time in a static scene (dynamic: false)"
    for c in cameras:
        ids, (H, W) = arrays.get(f"ids_{c}"), sizes[c]
        if ids is None or ids.dtype != np.uint8 or ids.shape != (num_frames, H, W):
            got = "none" if ids is None else f"{ids.dtype} {ids.shape}"
            return f"'ids_{c}' must be uint8 ({num_frames}, {H}, {W}), got {got}"
        bad = (ids > len(poses)) & (ids != NO_SURFACE)
        if bad.any():
            return f"'ids_{c}' has object id {int(ids[bad].max())}, but 'poses' has {len(poses)} object(s)"
    return None
