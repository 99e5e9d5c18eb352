"""Neural 3D Video (Neu3D / N3DV) → scene format: one scene folder, its static synchronised video cameras.

Source: Li et al., "Neural 3D Video Synthesis from Multi-view Video", CVPR 2022, read as LLFF (``load_llff.py``)
and hustvl/4DGaussians' ``neural_3D_dataset_NDC.py`` read it. Layout and conventions (COLMAP units, not metres;
4DGaussians holds ``cam00`` out for evaluation): ``data_prep/CONVERTERS.md``, "Neural 3D Video".
"""
from __future__ import annotations

import math
import os
from pathlib import Path

import cv2
import numpy as np

from .camera_conventions import c2w_gl_to_viewmat, c2w_llff_to_gl, camera_path, intrinsics
from .common import (
    check_downscale,
    downscale_rgb,
    downscaled_intrinsics,
    iter_video_frames,
    load_npy,
    require_file,
    select_frames,
    write_scene,
)

__all__ = ["convert_n3dv", "read_poses_bounds", "video_info"]


def read_poses_bounds(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Parse an LLFF ``poses_bounds.npy``: (c2w_llff (N, 3, 4) float64 LLFF axes, hwf (N, 3) = (height, width, focal)
    pixels, near_far (N, 2)). Raises FileNotFoundError: missing file; ValueError: not a finite (N, 17) array, or
    non-positive h, w or focal."""
    p = require_file(path, "poses_bounds.npy")
    arr = load_npy(p, "poses_bounds.npy")
    if arr.ndim != 2 or arr.shape[1] != 17 or arr.shape[0] < 1 or not np.issubdtype(arr.dtype, np.number):
        raise ValueError(f"{p} must be an (N_cams, 17) numeric array, got shape {arr.shape} dtype {arr.dtype}")
    arr = arr.astype(np.float64)
    if not np.isfinite(arr).all():
        raise ValueError(f"{p} holds non-finite values")
    P = arr[:, :15].reshape(-1, 3, 5)
    hwf = P[:, :, 4]
    if (hwf <= 0).any():
        raise ValueError(f"{p}: hwf (height, width, focal) must be > 0, got {hwf[(hwf <= 0).any(1)][0].tolist()}")
    return P[:, :, :4], hwf, arr[:, 15:]


def video_info(path: str | os.PathLike) -> tuple[int, float, int, int]:
    """(frame count, fps, width, height) of a video from its container (OpenCV ``VideoCapture``). Raises
    FileNotFoundError: missing file; ValueError: unreadable, or no positive frame count / fps / size."""
    p = require_file(path, "video")
    cap = cv2.VideoCapture(str(p))
    try:
        if not cap.isOpened():
            raise ValueError(f"could not open video {p}")
        n, fps = int(cap.get(cv2.CAP_PROP_FRAME_COUNT)), float(cap.get(cv2.CAP_PROP_FPS))
        w, h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
    finally:
        cap.release()
    if n < 1 or not math.isfinite(fps) or fps <= 0 or w < 1 or h < 1:
        raise ValueError(f"{p}: unusable video properties (frames={n}, fps={fps}, size={w}×{h})")
    return n, fps, w, h


def convert_n3dv(src: str | os.PathLike, out: str | os.PathLike, *, cameras: tuple[str, ...] | None = None,
                 downscale: int = 1, start: int = 0, stride: int = 1, max_frames: int | None = None,
                 replace: bool = False) -> Path:
    """Convert one N3DV scene folder ``src`` to the multi-camera dynamic scene ``out`` and return it. ``cameras``: video
    stems kept as camera names, first = reference (None: all, sorted); ``downscale``: integer factor
    (``cv2.INTER_AREA``); meta fps = video fps / stride. Raises FileNotFoundError: missing ``poses_bounds.npy`` or no
    ``cam*.mp4``; ValueError: a malformed ``poses_bounds.npy``; its row count differs from the number of videos; an
    unknown or repeated camera; videos of different fps; a video size whose aspect differs from hwf's; bad
    ``downscale``; a video shorter than its frame count says."""
    src = Path(src)
    c2w_llff, hwf, near_far = read_poses_bounds(src / "poses_bounds.npy")
    videos = sorted(src.glob("cam*.mp4"))
    if not videos:
        raise FileNotFoundError(f"no cam*.mp4 videos in N3DV folder {src}")
    if len(videos) != len(c2w_llff):
        raise ValueError(f"{src / 'poses_bounds.npy'} has {len(c2w_llff)} rows but {src} holds {len(videos)} "
                         "cam*.mp4 videos (rows are matched to the sorted video names)")
    row = {v.stem: k for k, v in enumerate(videos)}
    names = list(cameras) if cameras is not None else sorted(row)
    unknown = [n for n in names if n not in row]
    if unknown or len(set(names)) != len(names) or not names:
        raise ValueError(f"cameras must be distinct names among {sorted(row)}, got {names!r}")
    info = {n: video_info(src / f"{n}.mp4") for n in names}
    fps = info[names[0]][1]
    for n in names:
        if abs(info[n][1] - fps) > 1e-3 * fps:
            raise ValueError(f"{n}.mp4 runs at {info[n][1]} fps, {names[0]}.mp4 at {fps} fps: not synchronised")
    idx = select_frames(min(i[0] for i in info.values()), start, stride, max_frames)
    ts = np.asarray(idx, dtype=np.float64) / fps
    paths, sizes = {}, {}
    for n in names:
        k, (_, _, Wv, Hv) = row[n], info[n]
        h, w, f = hwf[k]
        sx, sy = Wv / w, Hv / h
        if abs(sx - sy) > 0.01 * sx:
            raise ValueError(f"{n}.mp4 is {Wv}×{Hv} but poses_bounds.npy row {k} has hwf size {w:g}×{h:g}: "
                             "different aspect ratios")
        check_downscale(downscale, Wv, Hv)
        K, W, H = downscaled_intrinsics(intrinsics(f * sx, f * sy, Wv / 2.0, Hv / 2.0)[0], Wv, Hv, downscale)
        V = c2w_gl_to_viewmat(c2w_llff_to_gl(c2w_llff[k]))
        paths[n] = camera_path(np.repeat(V[None], len(idx), axis=0), K, W, H, ts)
        sizes[n] = (Hv, Wv)

    def frames(name: str):
        for rgb in iter_video_frames(src / f"{name}.mp4", idx):
            if rgb.shape[:2] != sizes[name]:
                raise ValueError(f"{name}.mp4 decodes to {rgb.shape[1]}×{rgb.shape[0]} frames, its header says "
                                 f"{sizes[name][1]}×{sizes[name][0]}")
            yield downscale_rgb(rgb, downscale), None

    return write_scene(out, source="n3dv", dynamic=True, depth_source="none", fps=fps / stride, cameras=paths,
                       timestamps=ts, frames=frames, replace=replace,
                       extra={"source_id": src.resolve().name, "source_frames": idx, "downscale": downscale,
                              "near_far": {n: near_far[row[n]].tolist() for n in names},
                              "metric_scale": False, "units": "COLMAP/LLFF units (not metres)",
                              "evaluation_camera": "cam00 (held out by 4DGaussians for N3DV evaluation)"})
