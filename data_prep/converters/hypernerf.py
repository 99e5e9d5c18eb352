"""HyperNeRF / Nerfies captures → scene format: one capture, one camera (monocular) or two ("vrig").

Source: Park et al., "Nerfies: Deformable Neural Radiance Fields", ICCV 2021 and "HyperNeRF", SIGGRAPH Asia 2021;
google/nerfies (``camera.py`` ``Camera.project``/``from_json``/``scale``). Layout and conventions (undistorted
frames, COLMAP or nerfies-normalised units, nominal 15 Hz): ``data_prep/CONVERTERS.md``, "HyperNeRF / Nerfies".
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from diff4splat.io.structured import read_json

from .camera_conventions import INTEGER_CENTRE_SHIFT, camera_path, check_rotation, rigid
from .common import read_rgb_uint8, require_dir, select_frames, write_scene

__all__ = ["convert_hypernerf", "NerfiesCamera", "read_nerfies_camera", "undistort_rgb", "HYPERNERF_FPS"]

HYPERNERF_FPS = 15.0
"""Nominal frame rate of the captures' extracted frames, Hz (assumed: the files hold no rate; CONVERTERS.md)."""

_SPLIT_KEYS = {"all": "ids", "train": "train_ids", "val": "val_ids"}


@dataclass(frozen=True)
class NerfiesCamera:
    """One ``camera/<id>.json`` at full resolution, in our conventions: ``K`` (3, 3) pixels (centres at +0.5), ``R``
    (3, 3) world-to-camera OpenCV rotation, ``position`` (3,) camera centre, ``dist`` (5,) OpenCV (k1, k2, p1, p2,
    k3), ``size`` (W, H) pixels."""

    K: np.ndarray
    R: np.ndarray
    position: np.ndarray
    dist: np.ndarray
    size: tuple[int, int]


def _array(path: Path, data: dict, key: str, shape: tuple, default=None) -> np.ndarray:
    value = data.get(key, default)
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        a = np.zeros(0)
    if isinstance(value, bool) or a.shape != shape or not np.isfinite(a).all():
        raise ValueError(f"{path}: '{key}' must be finite numbers of shape {shape}, got {str(value)[:60]}")
    return a


def read_nerfies_camera(path: str | os.PathLike) -> NerfiesCamera:
    """Parse a Nerfies/HyperNeRF camera JSON (``tangential`` read as ``tangential_distortion``; absent skew, ratio,
    distortion: 0, 1, 0). Raises FileNotFoundError: missing file; ValueError: invalid JSON, a missing or malformed field
    (named), a non-positive focal length, ratio or image size, non-zero skew, or an orientation that is not a
    rotation."""
    path = Path(path)
    d = read_json(path, "HyperNeRF camera")
    if "tangential" in d and "tangential_distortion" not in d:
        d["tangential_distortion"] = d["tangential"]
    R = _array(path, d, "orientation", (3, 3))
    check_rotation(R, f"{path}: 'orientation'", "a rotation matrix (rows = camera axes)")
    f = float(_array(path, d, "focal_length", ()))
    ratio = float(_array(path, d, "pixel_aspect_ratio", (), 1.0))
    cx, cy = _array(path, d, "principal_point", (2,))
    size = _array(path, d, "image_size", (2,))
    if f <= 0 or ratio <= 0 or (size < 1).any() or (size != np.round(size)).any():
        raise ValueError(f"{path}: need focal_length > 0, pixel_aspect_ratio > 0 and integer image_size ≥ 1, got "
                         f"{f}, {ratio}, {size.tolist()}")
    if float(_array(path, d, "skew", (), 0.0)) != 0.0:
        raise ValueError(f"{path}: non-zero 'skew' is not supported (the scene format's Ks have no skew)")
    k1, k2, k3 = _array(path, d, "radial_distortion", (3,), [0.0, 0.0, 0.0])
    p1, p2 = _array(path, d, "tangential_distortion", (2,), [0.0, 0.0])
    K = np.array([[f, 0.0, cx], [0.0, f * ratio, cy], [0.0, 0.0, 1.0]])
    return NerfiesCamera(K, R, _array(path, d, "position", (3,)), np.array([k1, k2, p1, p2, k3]),
                         (int(size[0]), int(size[1])))


def undistort_rgb(rgb: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Undistort (H, W, 3) uint8 with pixel intrinsics ``K`` (centres at +0.5) and OpenCV ``dist``
    (k1, k2, p1, p2, k3); the result has intrinsics ``K`` and no distortion. All-zero ``dist`` → ``rgb``."""
    if not np.any(dist):
        return rgb
    K_cv = np.array(K, dtype=np.float64)
    K_cv[:2, 2] -= INTEGER_CENTRE_SHIFT  # OpenCV puts pixel centres at integer coordinates
    return cv2.undistort(rgb, K_cv, np.asarray(dist, dtype=np.float64), None, K_cv)


def _ids(src: Path, split: str) -> list[str]:
    if split not in _SPLIT_KEYS:
        raise ValueError(f"split must be one of {sorted(_SPLIT_KEYS)}, got {split!r}")
    path, key = src / "dataset.json", _SPLIT_KEYS[split]
    ids = read_json(path, "HyperNeRF dataset.json").get(key)
    if not isinstance(ids, list) or not ids or not all(isinstance(i, str | int) for i in ids):
        raise ValueError(f"{path}: '{key}' must be a non-empty list of ids")
    return [str(i) for i in ids]


def _group(src: Path, ids: list[str]) -> dict[int, list[tuple[int, str]]]:
    """camera_id → [(time_id, id)] sorted, from metadata.json."""
    path = src / "metadata.json"
    md = read_json(path, "HyperNeRF metadata.json")
    groups: dict[int, list[tuple[int, str]]] = {}
    for i in ids:
        e = md.get(i)
        if not isinstance(e, dict):
            raise ValueError(f"{path}: no entry for id {i!r}")
        t = e.get("time_id", e.get("warp_id"))
        c = e.get("camera_id")
        for key, v in (("time_id (or warp_id)", t), ("camera_id", c)):
            if isinstance(v, bool) or not isinstance(v, int):
                raise ValueError(f"{path}: [{i!r}]['{key}'] must be an integer, got {v!r}")
        groups.setdefault(c, []).append((t, i))
    return {c: sorted(v) for c, v in sorted(groups.items())}


def convert_hypernerf(src: str | os.PathLike, out: str | os.PathLike, *, scale: int = 1, split: str = "all",
                      normalize: bool = False, fps: float = HYPERNERF_FPS, start: int = 0, stride: int = 1,
                      max_frames: int | None = None, replace: bool = False) -> Path:
    """Convert one HyperNeRF/Nerfies capture ``src`` to a one- or two-camera dynamic scene ``out`` (``depth_source:
    "none"``) and return it. ``scale``: the ``rgb/<scale>x`` folder (intrinsics ÷ scale); ``split``: ``"all"``,
    ``"train"`` or ``"val"``; ``normalize``: nerfies' normalised world (X − center)·scale of ``scene.json``; ``fps``:
    nominal rate of time_ids, Hz (meta fps = fps / stride); ``start``, ``stride``, ``max_frames``: selection among the
    (common) time_ids. Raises FileNotFoundError: missing JSON, camera file, ``rgb/<scale>x`` folder or image;
    ValueError: bad options; a missing or malformed field in dataset.json, metadata.json, a camera file or scene.json
    (named); cameras without a common time_id; a repeated time_id in a multi-camera capture; a camera whose image size
    changes or differs from image_size / scale."""
    src = Path(src)
    if isinstance(scale, bool) or not isinstance(scale, int) or scale < 1:
        raise ValueError(f"scale must be an int ≥ 1 (the rgb/<scale>x folder), got {scale!r}")
    if isinstance(fps, bool) or not isinstance(fps, int | float) or not math.isfinite(fps) or fps <= 0:
        raise ValueError(f"fps must be a finite number > 0, got {fps!r}")
    groups = _group(src, _ids(src, split))
    if len(groups) == 1:
        (cam_id, seq), = groups.items()
        time_ids = [t for t, _ in seq]
        per_cam = {cam_id: [i for _, i in seq]}
    else:
        lookup = {}
        for c, seq in groups.items():
            lookup[c] = dict(seq)
            if len(lookup[c]) != len(seq):
                raise ValueError(f"camera_id {c} has a repeated time_id in {src / 'metadata.json'}: frames of "
                                 "several cameras can only be matched by unique time_ids")
        time_ids = sorted(set.intersection(*(set(m) for m in lookup.values())))
        if not time_ids:
            raise ValueError(f"the cameras {list(groups)} of {src} share no time_id (split {split!r})")
        per_cam = {c: [lookup[c][t] for t in time_ids] for c in groups}
    idx = select_frames(len(time_ids), start, stride, max_frames)
    ts = np.asarray([time_ids[k] for k in idx], dtype=np.float64) / fps
    center, s = np.zeros(3), 1.0
    scene_json = src / "scene.json"
    scene = read_json(scene_json, "HyperNeRF scene.json") if normalize or scene_json.is_file() else None
    if normalize:
        center, s = _array(scene_json, scene, "center", (3,)), float(_array(scene_json, scene, "scale", ()))
        if s <= 0:
            raise ValueError(f"{scene_json}: 'scale' must be > 0, got {s}")
    rgb_dir = require_dir(src / "rgb" / f"{scale}x", f"HyperNeRF rgb/{scale}x")
    names = {c: f"cam{k:02d}" for k, c in enumerate(per_cam)}
    paths, undist = {}, {}
    for c, ids in per_cam.items():
        cams = [read_nerfies_camera(src / "camera" / f"{ids[k]}.json") for k in idx]
        sizes = {(round(cam.size[0] / scale), round(cam.size[1] / scale)) for cam in cams}
        if len(sizes) != 1:
            raise ValueError(f"camera_id {c}: image_size changes between frames ({sorted(sizes)})")
        (W, H), = sizes
        K = np.stack([cam.K for cam in cams])
        K[:, :2] /= scale
        V = rigid(np.stack([cam.R for cam in cams]), np.stack([-cam.R @ ((cam.position - center) * s) for cam in cams]))
        paths[names[c]] = camera_path(V, K, W, H, ts)
        undist[names[c]] = [(rgb_dir / f"{ids[k]}.png", K[j], cams[j].dist) for j, k in enumerate(idx)]

    def frames(name: str):
        W, H = paths[name].width, paths[name].height
        for p, K, dist in undist[name]:
            rgb = read_rgb_uint8(p)
            if rgb.shape[:2] != (H, W):
                raise ValueError(f"{p} is {rgb.shape[1]}×{rgb.shape[0]}, expected image_size / {scale} = {W}×{H}")
            yield undistort_rgb(rgb, K, dist), None

    extra = {"source_id": src.resolve().name, "source_frames": [time_ids[k] for k in idx],
             "source_ids": {names[c]: [ids[k] for k in idx] for c, ids in per_cam.items()},
             "camera_ids": {names[c]: c for c in per_cam}, "split": split, "scale": scale,
             "normalized": bool(normalize), "metric_scale": False,
             "units": "nerfies normalised units (scene.json)" if normalize else "COLMAP units (not metres)"}
    if scene is not None:
        extra["scene_json"] = scene
    return write_scene(out, source="hypernerf", dynamic=True, depth_source="none", fps=fps / stride, cameras=paths,
                       timestamps=ts, frames=frames, replace=replace, extra=extra)
