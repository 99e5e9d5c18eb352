"""D-NeRF (Blender dynamic scenes) → scene format: one split of one object folder, one moving camera.

Source: Pumarola et al., "D-NeRF: Neural Radiance Fields for Dynamic Scenes", CVPR 2021 (``load_blender.py``) and
hustvl/4DGaussians' ``readCamerasFromTransforms``. Layout and conventions: ``data_prep/CONVERTERS.md``, "D-NeRF".
"""
from __future__ import annotations

import math
import os
from pathlib import Path

import cv2
import numpy as np

from diff4splat.io.structured import read_json

from .camera_conventions import c2w_gl_to_viewmat, camera_path, intrinsics
from .common import check_downscale, downscale_rgb, downscaled_intrinsics, require_file, select_frames, write_scene

__all__ = ["convert_dnerf", "read_dnerf_rgb", "DNERF_FPS", "DNERF_SPLITS"]

DNERF_FPS = 30.0
"""Nominal frame rate given to a split's frames, Hz (D-NeRF defines none)."""

DNERF_SPLITS = ("train", "val", "test")
"""The ``transforms_<split>.json`` files of a D-NeRF object."""

_BACKGROUNDS = {"white": 1.0, "black": 0.0}
_TIME_TOL = 1e-6  # the selection's first/last time must be 0/1 within this (float32 JSON values)


def read_dnerf_rgb(path: str | os.PathLike, background: float) -> np.ndarray:
    """Read a D-NeRF render as (H, W, 3) uint8 RGB, round(255 · (rgb·a + background·(1 − a))), ``background`` a grey
    level in [0, 1]. Raises FileNotFoundError: missing file; ValueError: undecodable or not 8/16-bit colour."""
    p = require_file(path, "D-NeRF image")
    img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    if img is None or img.dtype not in (np.uint8, np.uint16) or img.ndim != 3 or img.shape[2] not in (3, 4):
        got = None if img is None else (img.dtype, img.shape)
        raise ValueError(f"{p} must be an 8/16-bit RGB or RGBA image, got {got}")
    x = img.astype(np.float64) / np.iinfo(img.dtype).max
    rgb = x[..., 2::-1]  # BGR(A) → RGB
    if img.shape[2] == 4:
        a = x[..., 3:4]
        rgb = rgb * a + background * (1.0 - a)
    return np.clip(np.round(rgb * 255.0), 0, 255).astype(np.uint8)


def _image_path(src: Path, file_path: str) -> Path:
    p = src / file_path
    return p if p.suffix.lower() == ".png" else p.with_name(p.name + ".png")


def convert_dnerf(src: str | os.PathLike, out: str | os.PathLike, *, split: str = "train",
                  background: str = "white", downscale: int = 1, fps: float = DNERF_FPS, start: int = 0,
                  stride: int = 1, max_frames: int | None = None, replace: bool = False) -> Path:
    """Convert one split (``"train"``, ``"val"``, ``"test"``) of the D-NeRF object folder ``src`` to a one-camera
    dynamic scene ``out`` (``depth_source: "none"``) and return it. ``background``: ``"white"`` or ``"black"``;
    ``downscale``: integer factor (``cv2.INTER_AREA``); ``fps``: nominal, Hz (timestamps = time · (N − 1) / fps; meta
    fps = fps / stride); ``start``, ``stride``, ``max_frames``: the selection in time order. Raises FileNotFoundError:
    missing JSON or image; ValueError: bad ``split``/``background``/``downscale``/``fps``; a missing or malformed
    ``camera_angle_x``, ``frames``, ``file_path``, ``time`` or ``transform_matrix`` (named with its frame index); images
    of different sizes; a selection whose times do not span [0, 1]."""
    src = Path(src)
    if split not in DNERF_SPLITS:
        raise ValueError(f"split must be one of {DNERF_SPLITS}, got {split!r}")
    if background not in _BACKGROUNDS:
        raise ValueError(f"background must be one of {sorted(_BACKGROUNDS)}, got {background!r}")
    if isinstance(fps, bool) or not isinstance(fps, int | float) or not math.isfinite(fps) or fps <= 0:
        raise ValueError(f"fps must be a finite number > 0, got {fps!r}")
    json_path = src / f"transforms_{split}.json"
    meta = read_json(json_path, "D-NeRF transforms")
    angle = meta.get("camera_angle_x")
    if isinstance(angle, bool) or not isinstance(angle, int | float) or not 0 < angle < math.pi:
        raise ValueError(f"{json_path}: 'camera_angle_x' must be a number in (0, π) radians, got {angle!r}")
    frames_meta = meta.get("frames")
    if not isinstance(frames_meta, list) or not frames_meta:
        raise ValueError(f"{json_path}: 'frames' must be a non-empty list")
    times, paths, c2w = [], [], []
    for k, fr in enumerate(frames_meta):
        t = fr.get("time") if isinstance(fr, dict) else None
        if isinstance(t, bool) or not isinstance(t, int | float) or not 0.0 <= t <= 1.0:
            raise ValueError(f"{json_path}: frames[{k}]['time'] must be a number in [0, 1], got {t!r}")
        if not isinstance(fr.get("file_path"), str):
            raise ValueError(f"{json_path}: frames[{k}]['file_path'] must be a string")
        try:
            M = np.asarray(fr.get("transform_matrix"), dtype=np.float64)
        except (TypeError, ValueError):
            M = np.zeros(0)
        if M.shape != (4, 4) or not np.isfinite(M).all():
            raise ValueError(f"{json_path}: frames[{k}]['transform_matrix'] must be a finite 4×4 matrix")
        times.append(float(t))
        paths.append(_image_path(src, fr["file_path"]))
        c2w.append(M)
    order = np.argsort(np.asarray(times), kind="stable")
    idx = [int(order[i]) for i in select_frames(len(order), start, stride, max_frames)]
    sel_times = np.asarray([times[i] for i in idx])
    if abs(sel_times[0]) > _TIME_TOL or (len(idx) > 1 and abs(sel_times[-1] - 1.0) > _TIME_TOL):
        raise ValueError(
            f"{json_path}: the selected frames' times span [{sel_times[0]:g}, {sel_times[-1]:g}], not [0, 1]; the "
            "scene format normalises times to the first and last frame, so the stored times would differ from "
            "D-NeRF's 'time' values — select frames that include time 0 and time 1")
    H0, W0 = read_dnerf_rgb(paths[idx[0]], _BACKGROUNDS[background]).shape[:2]
    check_downscale(downscale, W0, H0)
    f = 0.5 * W0 / math.tan(0.5 * float(angle))
    K, W, H = downscaled_intrinsics(intrinsics(f, f, W0 / 2.0, H0 / 2.0)[0], W0, H0, downscale)
    ts = sel_times * (len(frames_meta) - 1) / fps
    cams = {"cam00": camera_path(c2w_gl_to_viewmat(np.stack([c2w[i] for i in idx])), K, W, H, ts)}

    def frames(_name: str):
        for i in idx:
            rgb = read_dnerf_rgb(paths[i], _BACKGROUNDS[background])
            if rgb.shape[:2] != (H0, W0):
                raise ValueError(f"{paths[i]} is {rgb.shape[1]}×{rgb.shape[0]}, the split's first image {W0}×{H0}")
            yield downscale_rgb(rgb, downscale), None

    return write_scene(out, source="dnerf", dynamic=True, depth_source="none", fps=fps / stride, cameras=cams,
                       timestamps=ts, frames=frames, replace=replace,
                       extra={"source_id": f"{src.resolve().name}/{split}",
                              "source_frames": [frames_meta[i]["file_path"] for i in idx],
                              "background": background, "downscale": downscale, "metric_scale": False,
                              "units": "Blender scene units (not known to be metres)"})
