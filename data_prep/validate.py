"""Validation of scene folders against ``data_prep/FORMAT.md`` (``data_prep validate DIR``): every file is decoded
and each problem names its file once; a path that is not a regular file (FIFO, folder, symlink loop, dangling link)
is reported as what it is and never opened.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from diff4splat.io import load_cameras_json, load_depth_exr
from diff4splat.io.inputs import check_input_file

from .scene_files import (
    CAMERAS_FILE,
    CAPTION_FILE,
    DEPTH_DIR,
    DEPTH_SUFFIX,
    META_FILE,
    OBJECTS_FILE,
    RGB_DIR,
    RGB_SUFFIX,
    SYNC_TOLERANCE_S,
    TIMES_TOLERANCE,
    TRACKS_FILE,
    SceneMeta,
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

__all__ = ["Problem", "validate_scene", "validate_path", "is_scene_dir", "summarize"]

STATIC_TRACK_TOLERANCE_M = 1e-6
"""A static scene's tracks may move by at most this many metres."""


@dataclass(frozen=True)
class Problem:
    """One violation of the format: the file (or folder) and what is wrong with it. ``scene`` (not compared): the
    scene folder it belongs to, None for a problem of a dataset root itself."""

    file: Path
    message: str
    scene: Path | None = field(default=None, compare=False)

    def __str__(self) -> str:
        return f"{self.file}: {self.message}"


def is_scene_dir(path: str | os.PathLike) -> bool:
    """True if ``path`` looks like one scene (has ``meta.json`` or a ``<cam>/cameras.json``), not a dataset root."""
    path = Path(path)
    if is_scene(path):
        return True
    return any(c.is_dir() and (c / CAMERAS_FILE).is_file() for c in path.iterdir()) if path.is_dir() else False


def _reason(e: Exception, path: Path) -> str:
    """``e``'s message without its leading ``<path>: `` or ``<what>: <path> ``; a path elsewhere becomes "file"."""
    text, name = str(e), str(path)
    if text.startswith(f"{name}: "):
        return text[len(name) + 2:]
    what, sep, rest = text.partition(f": {name} ")
    if sep and ":" not in what:
        return rest.removeprefix("is ") if rest.startswith("is not ") else rest
    return text.replace(name, "file")


def _file_problem(path: Path, missing: str = "missing file") -> str | None:
    """Why ``path`` is not a readable regular file (``missing``, or what it is, from ``check_input_file``), or None."""
    try:
        check_input_file(path, "file")
    except FileNotFoundError as e:
        reason = _reason(e, path)
        return missing if reason.startswith("does not exist") else reason
    except ValueError as e:
        return _reason(e, path).replace("not a file", "not a regular file")
    return None


def _optional_file_problem(problems: list[Problem], path: Path) -> bool:
    """Report an optional file that is there but not a regular file; True when there is a regular file to read."""
    if not (path.exists() or path.is_symlink()):  # also a dangling link or a loop
        return False
    why = _file_problem(path)
    if why is not None:
        problems.append(Problem(path, why))
    return why is None


def _check_frames(problems: list[Problem], folder: Path, suffix: str, T: int) -> list[Path]:
    """Report missing frame files and unexpected files; return the existing expected files in order."""
    expected = [folder / frame_name(i, suffix) for i in range(T)]
    if not folder.is_dir():
        problems.append(Problem(folder, "missing folder"))
        return []
    names = {p.name for p in expected}
    for p in sorted(folder.iterdir()):
        if p.name not in names and not p.name.startswith("."):
            problems.append(Problem(
                p, f"unexpected file (frames are {frame_name(0, suffix)} … {frame_name(T - 1, suffix)})"))
    present = []
    for p in expected:
        why = _file_problem(p, "missing frame")
        if why is None:
            present.append(p)
        else:
            problems.append(Problem(p, why))
    return present


def _check_camera(problems: list[Problem], scene: Path, name: str, meta: SceneMeta,
                  ref_ts: np.ndarray | None) -> tuple[np.ndarray | None, tuple[int, int] | None]:
    """Validate one camera folder; returns its timestamps and its (height, width) (each None if unreadable)."""
    folder, T = scene / name, meta.num_frames
    if not folder.is_dir():
        problems.append(Problem(folder, "missing camera folder (listed in meta.json 'cameras')"))
        return None, None
    cam_file = folder / CAMERAS_FILE
    size, ts = None, None
    why = _file_problem(cam_file)
    if why is not None:
        problems.append(Problem(cam_file, why))
    else:
        try:
            path = load_cameras_json(cam_file)
            size = (path.height, path.width)
            if len(path) != T:
                problems.append(Problem(cam_file, f"has {len(path)} cameras, meta.json num_frames is {T}"))
        except (ValueError, FileNotFoundError) as e:  # the file is reported once: its timestamps are not read
            problems.append(Problem(cam_file, _reason(e, cam_file)))
            path = None
        if path is not None:
            try:
                ts = read_timestamps(cam_file)
            except ValueError as e:
                problems.append(Problem(cam_file, _reason(e, cam_file)))
        if ts is not None and ts.shape != (T,):
            problems.append(Problem(cam_file, f"'timestamps' has {ts.size} values, num_frames is {T}"))
            ts = None
        if ts is not None and path is not None and len(path) == T:
            err = float(np.abs(timestamps_to_times(ts) - path.times.double().cpu().numpy()).max())
            if err > TIMES_TOLERANCE:
                problems.append(Problem(
                    cam_file, f"'times' differ from the normalised 'timestamps' by {err:.3g} (> {TIMES_TOLERANCE})"))
        if ts is not None and ref_ts is not None and float(np.abs(ts - ref_ts).max()) > SYNC_TOLERANCE_S:
            problems.append(Problem(cam_file, f"'timestamps' differ from the reference camera {meta.cameras[0]!r} "
                                              f"by {float(np.abs(ts - ref_ts).max()):.3g} s (not synchronised)"))

    for f in _check_frames(problems, folder / RGB_DIR, RGB_SUFFIX, T):
        try:
            img = read_rgb(f)
        except ValueError as e:
            problems.append(Problem(f, _reason(e, f)))
            continue
        why = None if size is None else size_problem("image", img.shape, size)
        if why is not None:
            problems.append(Problem(f, why))

    depth_dir = folder / DEPTH_DIR
    if meta.depth_source == "none":
        if depth_dir.exists():
            problems.append(Problem(depth_dir, "depth folder present but meta.json depth_source is 'none'"))
        return ts, size
    for f in _check_frames(problems, depth_dir, DEPTH_SUFFIX, T):
        try:
            z = load_depth_exr(f)
        except ValueError as e:
            problems.append(Problem(f, _reason(e, f)))
            continue
        for why in (None if size is None else size_problem("depth", z.shape, size), depth_values_problem(z)):
            if why is not None:
                problems.append(Problem(f, why))
    return ts, size


def _read_npz(problems: list[Problem], f: Path) -> dict[str, np.ndarray] | None:
    """Every array of the .npz ``f``, or None with the problem recorded."""
    try:
        with np.load(f, allow_pickle=False) as data:
            return {k: np.asarray(data[k]) for k in data.files}
    except Exception as e:  # numpy raises ValueError/OSError/zipfile errors for corrupt files
        problems.append(Problem(f, f"could not read as .npz: {e}"))
        return None


def _check_tracks(problems: list[Problem], f: Path, meta: SceneMeta) -> None:
    arrays = _read_npz(problems, f)
    if arrays is None:
        return
    missing = [k for k in ("points", "visibility") if k not in arrays]
    if missing:
        problems.append(Problem(f, f"missing array(s) {missing} (has {sorted(arrays)})"))
        return
    pts, vis, T = arrays["points"], arrays["visibility"], meta.num_frames
    if pts.dtype != np.float32 or pts.ndim != 3 or pts.shape[1:] != (T, 3) or pts.shape[0] < 1:
        problems.append(Problem(f, f"'points' must be float32 (P, {T}, 3) with P ≥ 1, got {pts.dtype} {pts.shape}"))
        return
    if vis.dtype != np.bool_ or vis.shape != pts.shape[:2]:
        problems.append(Problem(f, f"'visibility' must be bool {pts.shape[:2]}, got {vis.dtype} {vis.shape}"))
    if not np.isfinite(pts).all():
        problems.append(Problem(f, f"'points' has {int((~np.isfinite(pts)).sum())} non-finite value(s)"))
    elif not meta.dynamic:
        motion = float(np.abs(pts - pts[:, :1]).max())
        if motion > STATIC_TRACK_TOLERANCE_M:
            problems.append(Problem(f, f"tracks move by up to {motion:.3g} m in a static scene (dynamic: false)"))


def _check_objects(problems: list[Problem], f: Path, meta: SceneMeta, sizes: dict[str, tuple[int, int] | None]
                   ) -> None:
    if any(size is None for size in sizes.values()):  # a camera file problem is reported with its camera
        return
    arrays = _read_npz(problems, f)
    if arrays is None:
        return
    why = objects_problem(arrays, meta.cameras, sizes, meta.num_frames, meta.dynamic)
    if why is not None:
        problems.append(Problem(f, why))


def validate_scene(path: str | os.PathLike) -> list[Problem]:
    """Check one scene folder against every rule of FORMAT.md, decoding every file; never raises for a bad scene.

    Returns:
        Problems in file order; empty if the scene is valid. If ``meta.json`` is missing or invalid
        only that problem is reported (T and the cameras are unknown).
    """
    scene = Path(path)
    return [replace(p, scene=scene) for p in _scene_problems(scene)]


def _scene_problems(scene: Path) -> list[Problem]:
    """:func:`validate_scene` before each problem is given its scene."""
    if not scene.is_dir():
        return [Problem(scene, "not a folder")]
    meta_file = scene / META_FILE
    why = _file_problem(meta_file)
    if why is not None:
        return [Problem(meta_file, why)]
    try:
        meta = SceneMeta.load(meta_file)
    except ValueError as e:
        return [Problem(meta_file, _reason(e, meta_file))]
    problems: list[Problem] = []
    cap = scene / CAPTION_FILE
    if _optional_file_problem(problems, cap):
        try:
            text = cap.read_bytes().decode("utf-8").strip()
            if not text or "\n" in text or "\r" in text:
                problems.append(Problem(cap, "caption must be one non-empty line"))
        except UnicodeDecodeError as e:
            problems.append(Problem(cap, f"not UTF-8 text: {e}"))
    ref_ts, sizes = None, {}
    for k, name in enumerate(meta.cameras):
        ts, sizes[name] = _check_camera(problems, scene, name, meta, ref_ts)
        if k == 0:
            ref_ts = ts
    for c in sorted(scene.iterdir()):
        if c.is_dir() and c.name not in meta.cameras and (c / CAMERAS_FILE).exists():
            problems.append(Problem(c, "camera folder not listed in meta.json 'cameras'"))
    tracks = scene / TRACKS_FILE
    if _optional_file_problem(problems, tracks):
        _check_tracks(problems, tracks, meta)
    objects = scene / OBJECTS_FILE
    if _optional_file_problem(problems, objects):
        _check_objects(problems, objects, meta, sizes)
    return problems


def validate_path(path: str | os.PathLike) -> tuple[int, list[Problem]]:
    """Validate one scene folder or every scene of a dataset root (:func:`is_scene_dir` decides); in a root, each
    non-hidden sub-folder without ``meta.json``, or no scene at all, is a problem. Returns (number of scenes checked,
    problems). Raises FileNotFoundError: ``path`` is not a folder."""
    path = Path(path)
    if not path.is_dir():
        raise FileNotFoundError(f"not a folder: {path}")
    if is_scene_dir(path):
        return 1, validate_scene(path)
    scenes = list_scenes(path)
    problems: list[Problem] = []
    for d in sorted(path.iterdir()):
        if d.is_dir() and not d.name.startswith(".") and d not in scenes:
            why = _file_problem(d / META_FILE)
            problems.append(Problem(d / META_FILE, f"{why} (sub-folder of a dataset root is not a scene)"))
    if not scenes and not problems:
        problems.append(Problem(path, "no scene folders (sub-folders with meta.json) found"))
    for s in scenes:
        problems.extend(validate_scene(s))
    return len(scenes), problems


def summarize(num_scenes: int, problems: list[Problem]) -> str:
    """The summary line of ``data_prep validate``: problems in scenes, the scenes they are in, and the sub-folders of
    a dataset root that are not scenes."""
    in_scenes = [p for p in problems if p.scene is not None]
    bad = len({p.scene for p in in_scenes})
    text = f"{num_scenes} scene(s) checked: " + (f"{len(in_scenes)} problem(s) in {bad} scene(s)" if in_scenes
                                                 else "all valid")
    others = len(problems) - len(in_scenes)
    return text + (f"; {others} sub-folder(s) not a scene" if others else "")
