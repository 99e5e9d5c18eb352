"""The dataset scene format (version 1, specified in ``data_prep/FORMAT.md``): one folder per scene.

:class:`SceneWriter` writes a scene atomically (complete or absent); :class:`SceneReader` (:func:`load_scene`)
reads ``meta.json`` on open and everything else on demand. The constants, ``meta.json`` and the single-file
readers of :mod:`data_prep.scene_files` are re-exported here.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np
from torch import Tensor

from diff4splat.cameras import CameraPath
from diff4splat.io import load_cameras_json, load_depth_exr, output_dir, save_cameras_json, save_depth_exr, save_image
from diff4splat.utils.checks import is_int

from .engine import fault_point
from .scene_files import (
    CAMERAS_FILE,
    CAPTION_FILE,
    DEPTH_DIR,
    DEPTH_SOURCES,
    DEPTH_SUFFIX,
    FORMAT_VERSION,
    META_FILE,
    OBJECTS_FILE,
    RGB_DIR,
    RGB_SUFFIX,
    SYNC_TOLERANCE_S,
    TIMES_TOLERANCE,
    TRACKS_FILE,
    SceneMeta,
    check_camera_name,
    depth_values_problem,
    frame_name,
    is_scene,
    list_scenes,
    objects_problem,
    read_rgb,
    read_timestamps,
    size_problem,
    timestamps_to_times,
)
from .validate import validate_scene

__all__ = ["FORMAT_VERSION", "SCENE_KIND", "DEPTH_SOURCES", "SYNC_TOLERANCE_S", "TIMES_TOLERANCE", "SceneMeta",
           "SceneWriter", "SceneReader", "load_scene", "list_scenes", "check_dataset_root", "frame_name",
           "check_camera_name", "read_rgb", "read_timestamps", "timestamps_to_times"]

SCENE_KIND = "scene"
"""Output kind of a scene folder (:data:`diff4splat.io.MARKER`); ``replace=True`` replaces only these."""


def _check_depth(depth: Tensor | np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    if isinstance(depth, Tensor):
        depth = depth.detach().cpu().numpy()
    z = np.asarray(depth, dtype=np.float32)
    if z.shape != shape:
        raise ValueError(f"depth must have shape (H, W) = {shape}, got {z.shape}")
    bad = np.isnan(z) | (z <= 0) | np.isneginf(z)
    if bad.any():
        raise ValueError(f"depth has {int(bad.sum())} NaN, -inf or non-positive value(s); mark invalid pixels as +inf")
    return z


class SceneWriter:
    """Write the scene folder ``path`` atomically (FORMAT.md), as a context manager: it is built in a temporary folder
    beside ``path`` and renamed onto it when the block exits without error and every camera has all T RGB frames (and T
    depth frames unless ``depth_source == "none"``); on any error ``path`` is left as it was. ``source`` …
    ``depth_shift``, ``extra`` (more JSON keys): the meta fields (:class:`SceneMeta`; ``cameras`` is filled by
    :meth:`add_camera`). ``replace``: replace a scene folder written by this writer; ``replace_flag``: the option named
    in the refusal; ``validate``: check the folder (:func:`data_prep.validate.validate_scene`) first. Raises ValueError:
    invalid meta fields (on construction) or an incomplete/invalid scene (on exit); FileExistsError: ``path`` exists and
    ``replace`` is false; OutputDirError: ``path`` may not be written (a file, a folder that is not a scene written
    here, …)."""

    def __init__(self, path: str | os.PathLike, *, source: str, dynamic: bool, depth_source: str,
                 num_frames: int, fps: float, depth_scale: float = 1.0, depth_shift: float = 0.0,
                 extra: dict[str, Any] | None = None, replace: bool = False, validate: bool = True,
                 replace_flag: str | None = None) -> None:
        self.path = Path(path)
        # cameras is a placeholder until add_camera; validated now so bad meta fails before any IO
        self.meta = SceneMeta(source=source, dynamic=dynamic, depth_source=depth_source, num_frames=num_frames,
                              cameras=["cam00"], fps=fps, depth_scale=depth_scale, depth_shift=depth_shift,
                              extra=dict(extra or {}))
        self.meta.cameras = []
        self.replace, self.validate, self.replace_flag = replace, validate, replace_flag
        self._ctx = None
        self._tmp: Path | None = None
        self._sizes: dict[str, tuple[int, int]] = {}
        self._written: dict[str, tuple[set[int], set[int]]] = {}

    def __enter__(self) -> SceneWriter:
        self._ctx = output_dir(self.path, kind=SCENE_KIND, replace=self.replace, parents=True, overwrite_flag=None,
                               replace_flag=self.replace_flag)
        self._tmp = self._ctx.__enter__()
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        ctx = self._ctx
        try:
            if exc_type is None:
                try:
                    self._finish()
                except BaseException as e:  # discard the temporary folder, re-raise
                    ctx.__exit__(type(e), e, e.__traceback__)
                    raise
            return bool(ctx.__exit__(exc_type, exc, tb))
        finally:
            self._ctx = self._tmp = None

    @property
    def tmp_dir(self) -> Path:
        """The temporary folder being written (only inside the ``with`` block)."""
        if self._tmp is None or self._ctx is None:
            raise RuntimeError("SceneWriter is used outside its 'with' block")
        return self._tmp

    def add_camera(self, name: str, cameras: CameraPath, timestamps: np.ndarray | Tensor | None = None) -> None:
        """Add camera ``name`` (``[A-Za-z0-9_.-]+``; the first is the reference) and write its ``cameras.json``.
        ``cameras``: T = num_frames cameras; ``timestamps``: (T,) non-decreasing seconds whose normalisation (FORMAT.md)
        equals ``cameras.times``; None → times·(T−1)/fps. Raises ValueError: a bad or duplicate name, a path of the
        wrong length, or timestamps of the wrong shape, non-finite, decreasing, inconsistent with ``cameras.times`` or
        the reference camera's."""
        root = self.tmp_dir
        T = self.meta.num_frames
        if name in self._sizes:
            raise ValueError(f"camera {name!r} was already added")
        check_camera_name(name)
        cameras.validate()
        if len(cameras) != T:
            raise ValueError(f"camera {name!r} has {len(cameras)} frames, num_frames is {T}")
        times = cameras.times.detach().cpu().double().numpy()
        if timestamps is None:
            ts = times * (T - 1) / self.meta.fps
        else:
            if isinstance(timestamps, Tensor):
                timestamps = timestamps.detach().cpu().numpy()
            ts = np.asarray(timestamps, dtype=np.float64)
            if ts.shape != (T,) or not np.isfinite(ts).all() or (T > 1 and (np.diff(ts) < 0).any()):
                raise ValueError(f"timestamps of {name!r} must be ({T},) finite non-decreasing seconds, "
                                 f"got shape {ts.shape}")
            err = np.abs(timestamps_to_times(ts) - times).max()
            if err > TIMES_TOLERANCE:
                raise ValueError(f"camera {name!r}: times differ from the normalised timestamps by {err:.3g}")
        if self._sizes:
            ref = read_timestamps(root / self.meta.cameras[0] / CAMERAS_FILE)
            if np.abs(ref - ts).max() > SYNC_TOLERANCE_S:
                raise ValueError(f"camera {name!r} is not synchronised with {self.meta.cameras[0]!r} "
                                 "(timestamps differ)")
        cam_file = root / name / CAMERAS_FILE
        save_cameras_json(cam_file, cameras)
        data = json.loads(cam_file.read_text(encoding="utf-8"))
        data["timestamps"] = ts.tolist()
        cam_file.write_text(json.dumps(data, indent=1) + "\n", encoding="utf-8")
        self.meta.cameras.append(name)
        self._sizes[name] = (cameras.height, cameras.width)
        self._written[name] = (set(), set())

    def write_frame(self, camera: str, index: int, rgb: Tensor | np.ndarray,
                    depth: Tensor | np.ndarray | None = None) -> None:
        """Write frame ``index`` (in [0, T)) of ``camera``: ``rgb/{index:05d}.png`` and ``depth/{index:05d}.exr``.
        ``rgb``: (H, W, 3) uint8, or float in [0, 1] (rounded to 8 bits); ``depth``: (H, W) metric z-depth in metres, >
        0, +inf where invalid; required unless ``depth_source == "none"`` (then None). Raises ValueError: unknown
        camera, index out of range, wrong shapes, or NaN, −inf or ≤ 0 depth."""
        if camera not in self._sizes:
            raise ValueError(f"unknown camera {camera!r}; call add_camera first")
        if not is_int(index) or not 0 <= index < self.meta.num_frames:
            raise ValueError(f"frame index must be an int in [0, {self.meta.num_frames}), got {index!r}")
        H, W = self._sizes[camera]
        if tuple(rgb.shape) != (H, W, 3):
            raise ValueError(f"rgb of {camera!r} must have shape {(H, W, 3)}, got {tuple(rgb.shape)}")
        has_depth = self.meta.depth_source != "none"
        if has_depth != (depth is not None):
            raise ValueError(f"depth must be {'given' if has_depth else 'None'} "
                             f"for depth_source={self.meta.depth_source!r}")
        folder = self.tmp_dir / camera
        save_image(folder / RGB_DIR / frame_name(index, RGB_SUFFIX), rgb)
        self._written[camera][0].add(index)
        if depth is not None:
            save_depth_exr(folder / DEPTH_DIR / frame_name(index, DEPTH_SUFFIX), _check_depth(depth, (H, W)))
            self._written[camera][1].add(index)

    def write_tracks(self, points: np.ndarray | Tensor, visibility: np.ndarray | Tensor) -> None:
        """Write ``tracks.npz``: points (P, T, 3) metres world frame, visibility (P, T) bool (FORMAT.md). Raises
        ValueError: wrong shapes (T ≠ num_frames, P = 0), non-finite points, or moving tracks in a static scene."""
        pts = np.asarray(points.detach().cpu() if isinstance(points, Tensor) else points, dtype=np.float32)
        vis = np.asarray(visibility.detach().cpu() if isinstance(visibility, Tensor) else visibility)
        T = self.meta.num_frames
        if pts.ndim != 3 or pts.shape[1:] != (T, 3) or pts.shape[0] < 1:
            raise ValueError(f"points must have shape (P, {T}, 3) with P ≥ 1, got {pts.shape}")
        if vis.shape != pts.shape[:2] or vis.dtype != np.bool_:
            raise ValueError(f"visibility must be a bool array of shape {pts.shape[:2]}, got {vis.dtype} {vis.shape}")
        if not np.isfinite(pts).all():
            raise ValueError("points must be finite")
        if not self.meta.dynamic and np.abs(pts - pts[:, :1]).max() > 1e-6:
            raise ValueError("a static scene (dynamic=false) cannot have moving tracks")
        np.savez_compressed(self.tmp_dir / TRACKS_FILE, points=pts, visibility=vis)

    def write_objects(self, poses: np.ndarray, ids: dict[str, np.ndarray]) -> None:
        """Write ``objects.npz`` (FORMAT.md): ``poses`` (O, T, 3, 4) affine world maps of the O objects at each frame
        (stored float64), ``ids`` camera name → (T, H, W) uint8 id maps, for every added camera. Raises ValueError:
        a camera missing or unknown, or arrays that break FORMAT.md (:func:`data_prep.scene_files.objects_problem`)."""
        if set(ids) != set(self._sizes):
            raise ValueError(f"ids must give every camera's id maps ({sorted(self._sizes)}), got {sorted(ids)}")
        arrays = {"poses": np.asarray(poses, dtype=np.float64), **{f"ids_{c}": np.asarray(v) for c, v in ids.items()}}
        why = objects_problem(arrays, self.meta.cameras, self._sizes, self.meta.num_frames, self.meta.dynamic)
        if why is not None:
            raise ValueError(why)
        np.savez_compressed(self.tmp_dir / OBJECTS_FILE, **arrays)

    def write_caption(self, caption: str) -> None:
        """Write ``caption.txt``: one non-empty UTF-8 line. Raises ValueError otherwise."""
        if not isinstance(caption, str) or not caption.strip() or "\n" in caption.strip() or "\r" in caption:
            raise ValueError(f"caption must be one non-empty line of text, got {caption!r}")
        (self.tmp_dir / CAPTION_FILE).write_text(caption.strip() + "\n", encoding="utf-8")

    def _finish(self) -> None:
        if not self.meta.cameras:
            raise ValueError(f"scene {self.path} has no camera; call add_camera")
        T, has_depth = self.meta.num_frames, self.meta.depth_source != "none"
        for cam, (rgb_done, depth_done) in self._written.items():
            for kind, done in ((RGB_DIR, rgb_done), (DEPTH_DIR, depth_done if has_depth else set(range(T)))):
                if len(done) != T:
                    missing = sorted(set(range(T)) - done)
                    raise ValueError(f"scene {self.path}: camera {cam!r} misses {kind} frame(s) {missing[:5]}")
        self.meta.validate()
        (self.tmp_dir / META_FILE).write_text(json.dumps(self.meta.to_dict(), indent=1) + "\n", encoding="utf-8")
        if self.validate:
            problems = validate_scene(self.tmp_dir)
            if problems:
                raise ValueError(f"scene {self.path} is invalid: " + "; ".join(str(p) for p in problems[:5]))
        fault_point("write", self.path.name)  # a test's injected worker death: every file written, none renamed


class SceneReader:
    """Lazy read access to the scene folder ``path`` (FORMAT.md); only ``meta.json`` is read on open. Raises
    FileNotFoundError: ``path`` is not a folder or has no ``meta.json``; ValueError: an invalid ``meta.json``."""

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        if not self.path.is_dir():
            raise FileNotFoundError(f"scene folder not found: {self.path}")
        self.meta = SceneMeta.load(self.path / META_FILE)
        self._cameras: dict[str, CameraPath] = {}

    def __repr__(self) -> str:
        m = self.meta
        return f"SceneReader({str(self.path)!r}, source={m.source!r}, T={m.num_frames}, cameras={m.cameras})"

    @property
    def num_frames(self) -> int:
        """T, frames per camera."""
        return self.meta.num_frames

    @property
    def camera_names(self) -> list[str]:
        """Camera folder names, reference camera first."""
        return list(self.meta.cameras)

    @property
    def has_depth(self) -> bool:
        """False when ``depth_source == "none"``."""
        return self.meta.depth_source != "none"

    def _cam(self, camera: str) -> Path:
        if camera not in self.meta.cameras:
            raise ValueError(f"unknown camera {camera!r}; this scene has {self.meta.cameras}")
        return self.path / camera

    def _frame(self, camera: str, index: int, sub: str, suffix: str) -> Path:
        folder = self._cam(camera)
        if not is_int(index) or not 0 <= index < self.num_frames:
            raise ValueError(f"frame index must be an int in [0, {self.num_frames}), got {index!r}")
        return folder / sub / frame_name(index, suffix)

    def cameras(self, camera: str) -> CameraPath:
        """The :class:`CameraPath` of ``camera`` (cached): T viewmats (world-to-camera), Ks (pixels), times. Raises
        ValueError: unknown camera or invalid ``cameras.json``. FileNotFoundError: file missing."""
        if camera not in self._cameras:
            self._cameras[camera] = load_cameras_json(self._cam(camera) / CAMERAS_FILE)
        return self._cameras[camera]

    def timestamps(self, camera: str | None = None) -> np.ndarray:
        """(T,) float64 seconds of ``camera`` (default: the reference camera; all are synchronised)."""
        return read_timestamps(self._cam(camera or self.meta.cameras[0]) / CAMERAS_FILE)

    def _size(self, camera: str) -> tuple[int, int]:
        cams = self.cameras(camera)
        return cams.height, cams.width

    def rgb(self, camera: str, index: int) -> np.ndarray:
        """Frame ``index`` of ``camera``: (H, W, 3) float32 RGB in [0, 1], the size of its ``cameras.json``. Raises
        ValueError: unknown camera, index outside [0, T), an undecodable / non-RGB-8-bit file, or one of another size
        than its camera's; FileNotFoundError: the frame file is missing."""
        f = self._frame(camera, index, RGB_DIR, RGB_SUFFIX)
        img = read_rgb(f)
        why = size_problem("image", img.shape, self._size(camera))
        if why is not None:
            raise ValueError(f"{f}: {why}")
        return img

    def depth(self, camera: str, index: int) -> np.ndarray:
        """Frame ``index`` of ``camera``: (H, W) float32 metric z-depth in metres, +inf where invalid. Raises
        ValueError: the scene has no depth, unknown camera, index out of range, an EXR without a "Z" channel, of another
        size than its camera's or with NaN, −inf or ≤ 0 values; FileNotFoundError: the frame file is missing."""
        if not self.has_depth:
            raise ValueError(f"scene {self.path} has no depth (depth_source='none')")
        f = self._frame(camera, index, DEPTH_DIR, DEPTH_SUFFIX)
        z = load_depth_exr(f)
        for why in (size_problem("depth", z.shape, self._size(camera)), depth_values_problem(z)):
            if why is not None:
                raise ValueError(f"{f}: {why}")
        return z

    def tracks(self) -> tuple[np.ndarray, np.ndarray] | None:
        """``(points (P, T, 3) float32 metres world frame, visibility (P, T) bool)`` or None without tracks.npz. Raises
        ValueError: the file is unreadable or misses ``points``/``visibility``."""
        f = self.path / TRACKS_FILE
        if not f.is_file():
            return None
        try:
            with np.load(f, allow_pickle=False) as data:
                return np.asarray(data["points"]), np.asarray(data["visibility"])
        except (KeyError, ValueError, OSError) as e:
            raise ValueError(f"could not read {f}: {e}") from None

    def objects(self) -> tuple[np.ndarray, dict[str, np.ndarray]] | None:
        """``(poses (O, T, 3, 4) float64, camera name → ids (T, H, W) uint8)`` of ``objects.npz`` (FORMAT.md), or None
        without it. Raises ValueError: the file is unreadable or breaks FORMAT.md."""
        f = self.path / OBJECTS_FILE
        if not f.is_file():
            return None
        try:
            with np.load(f, allow_pickle=False) as data:
                arrays = {k: np.asarray(data[k]) for k in data.files}
        except (ValueError, OSError) as e:
            raise ValueError(f"could not read {f}: {e}") from None
        sizes = {c: self._size(c) for c in self.meta.cameras}
        why = objects_problem(arrays, self.meta.cameras, sizes, self.meta.num_frames, self.meta.dynamic)
        if why is not None:
            raise ValueError(f"{f}: {why}")
        return arrays["poses"], {c: arrays[f"ids_{c}"] for c in self.meta.cameras}

    @property
    def caption(self) -> str | None:
        """The caption (stripped), or None without caption.txt."""
        f = self.path / CAPTION_FILE
        return f.read_text(encoding="utf-8").strip() if f.is_file() else None

    def video(self, camera: str) -> np.ndarray:
        """All T RGB frames of ``camera``: (T, H, W, 3) float32 in [0, 1] (reads every file)."""
        return np.stack([self.rgb(camera, i) for i in range(self.num_frames)])


def load_scene(path: str | os.PathLike) -> SceneReader:
    """Open a scene folder lazily (:class:`SceneReader`); only ``meta.json`` is read and checked."""
    return SceneReader(path)


def check_dataset_root(out: Path, what: str = "dataset root") -> None:
    """Refuse to add scenes to ``out`` unless it is missing, empty or a dataset root (every entry but hidden ones, the
    writers' temporaries, a scene folder). Raises ValueError: the first entry that is not a scene folder, naming
    ``what`` (the flag) and ``out``."""
    if not out.is_dir():
        return
    for entry in sorted(out.iterdir()):
        if not entry.name.startswith(".") and not is_scene(entry):
            raise ValueError(f"{what} {out} holds {entry.name}, which is not a scene folder (no meta.json): synth adds "
                             "scenes to a new or empty folder or a dataset root only; choose another --out")
