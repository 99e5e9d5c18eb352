"""MatrixCity → scene format: one ``<block>`` folder of released poses and images, plus its depth folder.

Source: Li et al., "MatrixCity: A Large-scale City Dataset for City-scale Neural Rendering and Beyond", ICCV 2023
(README, ``scripts/load_data.py``). Layout and conventions: ``data_prep/CONVERTERS.md``, "MatrixCity".
"""
from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import OpenEXR

from .camera_conventions import c2w_gl_to_viewmat, camera_path, intrinsics, normalize_rotation, rigid
from .common import (
    finite_positive_or_inf,
    load_json_file,
    read_rgb_uint8,
    require_dir,
    require_file,
    select_frames,
    write_scene,
)

__all__ = ["convert_matrixcity", "read_matrixcity_depth", "MATRIXCITY_INVALID_DEPTH"]

MATRIXCITY_INVALID_DEPTH = 65504.0
"""Depth code (cm) with no geometry: the largest float16 (README / ``load_data.py``)."""


def read_matrixcity_depth(path: str | os.PathLike) -> np.ndarray:
    """A MatrixCity depth EXR (centimetres; first channel among R, Y, Z, then any) → (H, W) float32 metres, +inf
    where ≥ 65504 cm or non-finite. Raises FileNotFoundError: missing file; ValueError: unreadable EXR."""
    p = require_file(path, "MatrixCity depth")
    try:
        with OpenEXR.File(str(p), separate_channels=True) as f:
            chans = {k: np.array(v.pixels) for k, v in f.channels().items()}
    except Exception as e:
        raise ValueError(f"could not read {p} as EXR: {e}") from e
    name = next((c for c in ("R", "Y", "Z") if c in chans), sorted(chans)[0])
    cm = chans[name].astype(np.float64)
    return finite_positive_or_inf(np.where(cm >= MATRIXCITY_INVALID_DEPTH, np.inf, cm / 100.0))


def _image_path(src: Path, file_path: str) -> Path:
    """Resolve a frame's ``file_path`` relative to the block folder, else by file name inside it."""
    for cand in (src / file_path, src / Path(file_path).name):
        for p in (cand, cand.with_suffix(".png")):
            if p.is_file():
                return p
    raise FileNotFoundError(f"MatrixCity image for file_path {file_path!r} not found in {src}")


def convert_matrixcity(src: str | os.PathLike, out: str | os.PathLike, *, depth_dir: str | os.PathLike | None = None,
                       transforms: str = "transforms.json", metres_per_unit: float = 1.0, start: int = 0,
                       stride: int = 1, max_frames: int | None = None, fps: float = 10.0,
                       replace: bool = False) -> Path:
    """Convert one MatrixCity block folder ``src`` to the static scene ``out`` and return it. ``depth_dir``: folder of
    ``<image stem>.exr`` (None: ``depth_source="none"``); ``transforms``: the pose file in ``src``; ``metres_per_unit``:
    its position unit (1 for ``<block>/transforms.json``, 100 for ``pose/<block>``); ``fps``: nominal, Hz (frames are
    sampled along a path, not in time). Raises FileNotFoundError: missing files; ValueError: no intrinsics in the JSON,
    a transform that is not a uniformly scaled rotation, or images of another size than ``w``×``h``."""
    src = Path(src)
    meta = load_json_file(src / transforms, "MatrixCity transforms.json")
    frames_meta = meta.get("frames") or []
    W, H = (int(meta["w"]), int(meta["h"])) if "w" in meta and "h" in meta else (None, None)
    idx = select_frames(len(frames_meta), start, stride, max_frames)
    img_paths = [_image_path(src, frames_meta[f]["file_path"]) for f in idx]
    if W is None:
        H, W = read_rgb_uint8(img_paths[0]).shape[:2]
    if "fl_x" in meta:
        fx, fy = float(meta["fl_x"]), float(meta.get("fl_y", meta["fl_x"]))
    elif "camera_angle_x" in meta:
        fx = fy = 0.5 * W / math.tan(0.5 * float(meta["camera_angle_x"]))
    else:
        raise ValueError(f"{src / transforms} has neither 'fl_x' nor 'camera_angle_x'")
    K = intrinsics(fx, fy, float(meta.get("cx", W / 2.0)), float(meta.get("cy", H / 2.0)))[0]
    M = np.asarray([frames_meta[f]["transform_matrix"] for f in idx], dtype=np.float64)
    c2w = rigid(normalize_rotation(M[:, :3, :3], "transform_matrix rotation"), M[:, :3, 3] * metres_per_unit)
    ts = np.asarray(idx, dtype=np.float64) / fps
    cams = {"cam00": camera_path(c2w_gl_to_viewmat(c2w), K, W, H, ts)}
    ddir = require_dir(depth_dir, "MatrixCity depth") if depth_dir is not None else None

    def frames(_name: str):
        for p in img_paths:
            rgb = read_rgb_uint8(p)
            if rgb.shape[:2] != (H, W):
                raise ValueError(f"{p} has size {rgb.shape[1]}×{rgb.shape[0]}, transforms.json says {W}×{H}")
            yield rgb, (read_matrixcity_depth(ddir / f"{p.stem}.exr") if ddir is not None else None)

    return write_scene(out, source="matrixcity", dynamic=False, depth_source="ground_truth" if ddir else "none",
                       fps=fps / stride, cameras=cams, timestamps=ts, frames=frames, replace=replace,
                       extra={"source_id": src.resolve().name,
                              "source_frames": [str(frames_meta[f]["file_path"]) for f in idx]})
