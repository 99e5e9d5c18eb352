"""Stereo4D → scene format: one clip's annotation ``.npz`` and left rectified video, metric poses and 3D tracks.

Source: Jin et al., "Stereo4D: Learning How Things Move in 3D from Internet Stereo Videos", CVPR 2025 (stereo4d-code
README, ``rectify.py``). Layout and conventions: ``data_prep/CONVERTERS.md``, "Stereo4D".
"""
from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from .camera_conventions import c2w_cv_to_viewmat, camera_path, intrinsics
from .common import iter_video_frames, load_npz, only_stem, select_frames, write_scene

__all__ = ["convert_stereo4d", "decode_stereo4d_tracks", "STEREO4D_HFOV_DEG"]

STEREO4D_HFOV_DEG = 60.0
"""Horizontal field of view of the release's rectified perspective videos, degrees."""


def decode_stereo4d_tracks(lengths: np.ndarray, indices: np.ndarray, coords: np.ndarray, num_frames: int) -> np.ndarray:
    """Ragged Stereo4D tracks → (P, T, 3) float64 world points, NaN where a track is undefined. Raises ValueError: Σ
    lengths ≠ number of entries, or a frame index outside [0, num_frames)."""
    lengths = np.asarray(lengths, dtype=np.int64)
    indices = np.asarray(indices, dtype=np.int64)
    coords = np.asarray(coords, dtype=np.float64)
    if lengths.sum() != indices.size or coords.shape != (indices.size, 3):
        raise ValueError(f"track_lengths sum to {lengths.sum()} but there are {indices.size} indices "
                         f"/ {coords.shape} coordinates")
    if indices.size and (indices.min() < 0 or indices.max() >= num_frames):
        raise ValueError(f"track_indices must lie in [0, {num_frames})")
    out = np.full((lengths.size, num_frames, 3), np.nan)
    out[np.repeat(np.arange(lengths.size), lengths), indices] = coords
    return out


def convert_stereo4d(src: str | os.PathLike, out: str | os.PathLike, *, name: str | None = None,
                     hfov_deg: float = STEREO4D_HFOV_DEG, start: int = 0, stride: int = 1,
                     max_frames: int | None = None, max_tracks: int = 4096, replace: bool = False) -> Path:
    """Convert one Stereo4D clip (None: the only ``.npz`` of ``src``), left eye, to the scene ``out``; return it
    (dynamic, ``depth_source="none"``, timestamps from the npz). ``hfov_deg``: horizontal field of view of the rectified
    video, degrees; ``max_tracks``: at most this many tracks defined in every selected frame, evenly spaced (0: none),
    visible where in front of the camera and in the image. Raises ValueError: ambiguous clip, missing npz keys, or frame
    counts that disagree; FileNotFoundError: missing npz or video."""
    src = Path(src)
    if name is None:
        name = only_stem(src, "*.npz", "name", ".npz files")
    data = load_npz(src / f"{name}.npz", "Stereo4D npz", ("camera2world", "timestamps"),
                    ("track_lengths", "track_indices", "track_coordinates"))
    c2w = data["camera2world"].astype(np.float64)
    if c2w.shape[1:] == (3, 4):
        c2w = np.concatenate([c2w, np.broadcast_to([[[0.0, 0.0, 0.0, 1.0]]], (c2w.shape[0], 1, 4))], axis=1)
    T_src = c2w.shape[0]
    if data["timestamps"].shape != (T_src,):
        raise ValueError(f"timestamps has shape {data['timestamps'].shape}, camera2world has {T_src} frames")
    idx = select_frames(T_src, start, stride, max_frames)
    ts = data["timestamps"][idx].astype(np.float64) * 1e-6
    video = src / f"{name}-left_rectified.mp4"
    H, W = next(iter_video_frames(video, [0])).shape[:2]
    f = 0.5 * W / math.tan(math.radians(hfov_deg) / 2.0)
    viewmats = c2w_cv_to_viewmat(c2w[idx])
    K = intrinsics(f, f, W / 2.0, H / 2.0)[0]
    cams = {"cam00": camera_path(viewmats, K, W, H, ts)}

    tracks = None
    if max_tracks > 0 and "track_lengths" in data:
        pts = decode_stereo4d_tracks(data["track_lengths"], data["track_indices"], data["track_coordinates"],
                                     T_src)[:, idx]
        keep = np.flatnonzero(np.isfinite(pts).all(axis=(1, 2)))
        if keep.size > max_tracks:
            keep = keep[np.linspace(0, keep.size - 1, max_tracks).round().astype(int)]
        if keep.size:
            pts = pts[keep]
            cam = np.einsum("tij,ptj->pti", viewmats[:, :3, :3], pts) + viewmats[None, :, :3, 3]
            with np.errstate(divide="ignore", invalid="ignore"):
                uv = np.einsum("ij,ptj->pti", K, cam / cam[..., 2:3])[..., :2]
            vis = (cam[..., 2] > 0) & (uv[..., 0] >= 0) & (uv[..., 0] < W) & (uv[..., 1] >= 0) & (uv[..., 1] < H)
            tracks = (pts, vis)

    def frames(_name: str):
        for rgb in iter_video_frames(video, idx):
            yield rgb, None

    fps = (len(ts) - 1) / (ts[-1] - ts[0]) if len(ts) > 1 and ts[-1] > ts[0] else 30.0
    return write_scene(out, source="stereo4d", dynamic=True, depth_source="none", fps=fps, cameras=cams,
                       timestamps=ts, frames=frames, tracks=tracks, replace=replace,
                       extra={"source_id": name, "source_frames": idx, "hfov_deg": hfov_deg,
                              "tracks_visibility": "in front of the camera and inside the image "
                                                   "(no occlusion flag in the source)"})
