"""Stereo4D → scene format.

Source: Jin et al., "Stereo4D: Learning How Things Move in 3D from Internet Stereo Videos",
CVPR 2025, and the README of its code release (stereo4d-code). The released annotation of a clip
is one ``.npz``; the frames come from the YouTube VR180 video, rectified and cropped to a 60°
perspective view by the release's ``rectify.py``::

    <IN>/<name>.npz                      name, video_id, timestamps (T,) µs of the source video,
                                         camera2world (T, 3|4, 4) OpenCV axes, metres,
                                         track_lengths (P,), track_indices (ΣL,), track_coordinates (ΣL, 3)
    <IN>/<name>-left_rectified.mp4       T frames, square (512×512), 60° horizontal field of view

Tracks are stored ragged: track p occupies the next ``track_lengths[p]`` entries; entry j puts
``track_coordinates[j]`` (world metres) at frame ``track_indices[j]``; other frames are undefined.
The scale is metric (stereo baseline of the VR180 rig). Intrinsics follow from the perspective crop:
fx = fy = (W/2)/tan(hfov/2), principal point at the image centre. No dense depth is released.
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
    """Ragged Stereo4D tracks → (P, T, 3) float64 world points, NaN where a track is undefined.

    Raises:
        ValueError: Σ lengths ≠ number of entries, or a frame index outside [0, num_frames).
    """
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
    """Convert one Stereo4D clip (module docstring) to a scene folder (left eye).

    Args:
        src: folder with ``<name>.npz`` and ``<name>-left_rectified.mp4``.
        out: output scene folder.
        name: clip name; ``None`` when ``src`` holds exactly one ``.npz``.
        hfov_deg: horizontal field of view of the rectified video, degrees.
        start, stride, max_frames: frame selection.
        max_tracks: keep at most this many tracks defined in every selected frame (evenly spaced);
            0 writes no tracks.
        replace: replace an existing output folder.

    Returns:
        The scene folder (dynamic, ``depth_source="none"``, timestamps from the npz). Track
        visibility = in front of the camera and inside the image (the release has no occlusion flag
        for tracks; undefined entries are dropped with their track).

    Raises:
        ValueError: ambiguous clip, missing npz keys, or frame counts that disagree.
        FileNotFoundError: missing npz or video.
    """
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
