"""Drags taken from a clip's true motion, for evaluation (the drag rows of benchmarks/drags.py): what a user who
drags each moving object by where it truly goes would give :meth:`Diff4SplatPipeline.__call__`.

A moving object is a connected region of frame 0's valid pixels whose dense track (``ClipDataset``'s
``pixel_tracks``) moves more than :data:`MOVING_M`; its drag points are its pixel nearest the region's centroid, then
farthest-point samples; each point's 3D track is projected into the first camera (the photograph's pixels over the
clip's frames, frame 0 the pixel centre's projection).
"""
from __future__ import annotations

import cv2
import numpy as np
from torch import Tensor

from diff4splat.geometry.drags import Drags

__all__ = ["MOVING_M", "moving_objects", "true_drags"]

MOVING_M = 0.01
"""Displacement, metres, above which a pixel's surface point moves in the clip."""


def moving_objects(pixel_tracks: Tensor, valid: Tensor) -> np.ndarray:
    """(H, W) int32 labels of the moving objects (1, 2, …; 0: still or unknown) of frame 0: connected regions of
    ``valid`` (H, W) pixels whose ``pixel_tracks`` (T, H, W, 3) move more than :data:`MOVING_M`."""
    moved = (pixel_tracks - pixel_tracks[:1]).norm(dim=-1).amax(0) > MOVING_M
    mask = (moved & valid.bool()).cpu().numpy().astype(np.uint8)  # device: OpenCV labels on the host
    return cv2.connectedComponents(mask, connectivity=8)[1].astype(np.int32)


def true_drags(clip: dict, per_object: int = 1, min_pixels: int = 3) -> Drags | None:
    """``per_object`` drags on each moving object (module docstring) of a ``ClipDataset`` clip (CPU tensors; its
    ``pixel_tracks``, ``pixel_track_valid`` and ``Ks``), objects under ``min_pixels`` pixels left out; None when the
    clip has none. Times: the clip's frames, evenly spaced over [0, 1]."""
    tracks, K = clip["pixel_tracks"].double(), clip["Ks"][0].double()
    T, H, W = tracks.shape[:3]
    labels = moving_objects(tracks, clip["pixel_track_valid"])
    paths = []
    for i in range(1, int(labels.max()) + 1):
        ys, xs = np.nonzero(labels == i)
        if len(ys) < min_pixels:
            continue
        picks = [int(np.argmin((ys - ys.mean()) ** 2 + (xs - xs.mean()) ** 2))]
        while len(picks) < min(per_object, len(ys)):  # farthest-point sampling
            gap = np.min([(ys - ys[p]) ** 2 + (xs - xs[p]) ** 2 for p in picks], axis=0)
            picks.append(int(np.argmax(gap)))
        for p in picks:
            seen = tracks[:, ys[p], xs[p]] @ K.T  # (T, 3)
            uv = (seen[:, :2] / seen[:, 2:]).cpu().numpy()  # device: the drags are host arrays
            paths.append(uv - uv[0] + np.array([xs[p] + 0.5, ys[p] + 0.5]))
    if not paths:
        return None
    return Drags(np.linspace(0.0, 1.0, T), np.stack(paths), W, H)
