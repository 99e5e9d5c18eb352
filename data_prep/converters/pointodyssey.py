"""PointOdyssey → scene format: one sequence folder, one camera, ground-truth depth and 3D tracks.

Source: Zheng et al., "PointOdyssey: A Large-Scale Synthetic Dataset for Long-Term Point Tracking", ICCV 2023
(``pointodysseydataset*.py``). Layout and conventions: ``data_prep/CONVERTERS.md``, "PointOdyssey".
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .camera_conventions import camera_path
from .common import decode_scaled_uint16, load_npz, read_rgb_uint8, read_uint16_png, select_frames, write_scene

__all__ = ["convert_pointodyssey", "POINTODYSSEY_DEPTH_M_PER_UNIT", "POINTODYSSEY_FPS"]

POINTODYSSEY_DEPTH_M_PER_UNIT = 1000.0 / 65535.0
"""Depth PNG unit in metres (the release decodes depth16 / 65535 · 1000)."""

POINTODYSSEY_FPS = 30.0
"""Nominal frame rate, Hz (not stated in the annotation files; see CONVERTERS.md)."""

_ANNO_KEYS = ("trajs_3d", "visibs", "valids", "intrinsics", "extrinsics")


def convert_pointodyssey(src: str | os.PathLike, out: str | os.PathLike, *, start: int = 0, stride: int = 1,
                         max_frames: int | None = None, max_tracks: int = 4096, fps: float = POINTODYSSEY_FPS,
                         replace: bool = False) -> Path:
    """Convert one PointOdyssey sequence folder ``src`` to the scene ``out`` and return it: ``cam00``, ground-truth
    depth, tracks with visibility ``visibs & valids``. ``max_tracks``: at most this many tracks finite in every selected
    frame, evenly spaced (0: no ``tracks.npz``); ``fps``: source rate, Hz (meta fps = fps / stride). Raises
    FileNotFoundError: missing ``anno.npz`` or frame files; ValueError: ``anno.npz`` misses a key (named) or has
    inconsistent frame counts."""
    src = Path(src)
    anno = load_npz(src / "anno.npz", "PointOdyssey anno.npz", _ANNO_KEYS)
    T_src = anno["extrinsics"].shape[0]
    for k in _ANNO_KEYS:
        if anno[k].shape[0] != T_src:
            raise ValueError(f"anno.npz '{k}' has {anno[k].shape[0]} frames, extrinsics has {T_src}")
    idx = select_frames(T_src, start, stride, max_frames)
    ts = np.asarray(idx, dtype=np.float64) / fps
    first = read_rgb_uint8(src / "rgbs" / f"rgb_{idx[0]:05d}.jpg")
    H, W = first.shape[:2]
    cams = {"cam00": camera_path(anno["extrinsics"][idx], anno["intrinsics"][idx], W, H, ts)}

    def frames(_name: str):
        for f in idx:
            raw = read_uint16_png(src / "depths" / f"depth_{f:05d}.png")
            yield (read_rgb_uint8(src / "rgbs" / f"rgb_{f:05d}.jpg"),
                   decode_scaled_uint16(raw, POINTODYSSEY_DEPTH_M_PER_UNIT, invalid=(0, 65535)))

    tracks = None
    if max_tracks > 0:
        pts = np.swapaxes(anno["trajs_3d"][idx], 0, 1).astype(np.float64)  # (N, T, 3)
        vis = np.swapaxes(anno["visibs"][idx].astype(bool) & anno["valids"][idx].astype(bool), 0, 1)
        keep = np.flatnonzero(np.isfinite(pts).all(axis=(1, 2)))  # finite in every selected frame
        if keep.size > max_tracks:
            keep = keep[np.linspace(0, keep.size - 1, max_tracks).round().astype(int)]
        tracks = (pts[keep], vis[keep]) if keep.size else None
    return write_scene(out, source="pointodyssey", dynamic=True, depth_source="ground_truth", fps=fps / stride,
                       cameras=cams, timestamps=ts, frames=frames, tracks=tracks, replace=replace,
                       extra={"source_id": src.resolve().name, "source_frames": idx,
                              "tracks_visibility": "source visibs & valids"})
