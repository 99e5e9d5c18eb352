"""Drags: sparse motion of a photograph's pixels, made dense (docs/DESIGN.md, "Drags").

A drag moves one point of the photograph over the clip, as the motion controls of DragNUWA (Yin et al. 2023) and
Motion Prompting (Geng et al., CVPR 2025) do; :class:`Drags` holds N of them as piecewise-linear pixel tracks over
normalised clip time. :func:`drag_motion` makes them a dense 3D motion of the photograph's pixels without learning:

1. :func:`drag_segments`: the photograph is cut into regions of like colour and depth (Felzenszwalb & Huttenlocher's
   graph segmentation, IJCV 2004, OpenCV's ``ximgproc``, on CIELAB colour and log depth at
   :data:`SEGMENT_HEIGHT` pixels of height); the regions holding a drag's point move, the rest of the photograph stays.
2. Each dragged pixel takes the motion of the nearest drag in its region, a translation lifted to 3D along the
   surface the scene rests on (:func:`support_normal`: the plane of the depth map's largest upward-facing surface,
   fitted by RANSAC, Fischler & Bolles 1981): the dragged point's target is where the drag's pixel ray meets the
   plane through the point parallel to that surface, so a drag down the image moves an object on a floor toward the
   camera rather than into the floor. Where no such surface is found, or the ray meets the plane behind the camera
   or beyond :data:`LIFT_RANGE` of the point's depth, the drag is lifted at the point's own depth (parallel to the
   image plane).

Pixel (i, j) is centred at (j + 0.5, i + 0.5); x to the right, y down; depths are z-depths in metres; the motion is
in the camera's frame (the scene's world frame for the path's first camera).
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass

import cv2
import numpy as np
import torch
from torch import Tensor

__all__ = ["Drags", "parse_drag", "drags_from_flags", "drags_from_tracks", "drag_segments", "drag_motion",
           "support_normal", "SEGMENT_HEIGHT", "SEGMENT_K", "SEGMENT_SIGMA", "DEPTH_WEIGHT", "SUPPORT_TILT_DEG",
           "SUPPORT_INLIER", "SUPPORT_MIN_FRACTION", "SUPPORT_SPREAD", "LIFT_RANGE"]

SEGMENT_HEIGHT = 64
"""Height, pixels, at which :func:`drag_segments` cuts the photograph (regions then scale with the image)."""
SEGMENT_K = 50.0
"""Felzenszwalb's k at :data:`SEGMENT_HEIGHT`: larger gives larger regions (chosen on synthetic development clips,
docs/benchmarks.md "Drags")."""
SEGMENT_SIGMA = 0.0
"""Gaussian smoothing, pixels, before :func:`drag_segments` (smoothing makes an object's edge a band of its own)."""
DEPTH_WEIGHT = 96.0
"""Weight of log depth beside CIELAB colour (0–255 per channel) in :func:`drag_segments`: a depth ratio of ×2.7
weighs as 96 colour levels."""
SUPPORT_TILT_DEG = 60.0
"""A surface whose normal is within this angle of the camera's up (−y) may be the support of :func:`support_normal`."""
SUPPORT_INLIER = 0.02
"""RANSAC inlier distance of :func:`support_normal`, as a fraction of the median depth."""
SUPPORT_MIN_FRACTION = 0.1
"""The least fraction of the valid pixels a support plane of :func:`support_normal` holds."""
SUPPORT_SPREAD = 0.25
"""The least ratio of a support plane's inliers' two in-plane spreads (singular values): a surface, not a band."""
LIFT_RANGE = 1.15
"""A plane-lifted target farther than this factor from the dragged point's depth (or nearer than its inverse) falls
back to the constant-depth lift: a drag up the image is an object sliding away over the floor or one rising off it,
and only a small change of depth is taken as the first (chosen on the development sets among 1.15, 1.4 and 2,
docs/benchmarks.md "Drags")."""
_DRAG = re.compile(r"^\s*([^,:@]+),([^,:@]+):([^,:@]+),([^,:@]+)(?:@([^,:@]+))?\s*$")


@dataclass(frozen=True)
class Drags:
    """N drags of the photograph's pixels.

    Attributes:
        times: (K,) float64, increasing normalised clip times in [0, 1], ``times[0]`` = 0.
        positions: (N, K, 2) float64 pixels (x, y) of each point at each time; ``positions[:, 0]`` the points in the
            photograph. After the last time a point stays where it is; between times it moves linearly.
        width, height: the photograph's size, pixels, that the positions refer to.
    """

    times: np.ndarray
    positions: np.ndarray
    width: int
    height: int

    def __post_init__(self) -> None:
        t, p = self.times, self.positions
        if t.ndim != 1 or len(t) < 2 or t[0] != 0 or not (np.diff(t) > 0).all() or t[-1] > 1:
            raise ValueError(f"drag times must increase from 0 within [0, 1], got {t.tolist()}")
        if p.ndim != 3 or p.shape[1:] != (len(t), 2) or len(p) == 0:
            raise ValueError(f"drag positions must be (N ≥ 1, {len(t)}, 2), got {p.shape}")
        if not np.isfinite(p).all():
            raise ValueError("drags must be finite numbers (a NaN or inf was given)")
        x, y = p[:, 0, 0], p[:, 0, 1]
        outside = ~((x >= 0) & (x < self.width) & (y >= 0) & (y < self.height))
        if outside.any():
            i = int(np.argmax(outside))
            raise ValueError(f"drag {i + 1} starts at ({x[i]:g}, {y[i]:g}), outside the {self.width}×{self.height} "
                             f"photograph")

    def __len__(self) -> int:
        return len(self.positions)

    def at(self, t: float) -> np.ndarray:
        """(N, 2) pixel positions at normalised time ``t`` (linear between times, held after the last)."""
        t = min(max(float(t), 0.0), 1.0)
        return np.array([[np.interp(t, self.times, track[:, c]) for c in range(2)] for track in self.positions])

    def resized(self, box: tuple[int, int, int, int], width: int, height: int) -> Drags:
        """The drags in the crop ``box`` = (x0, y0, x1, y1) of the photograph resized to ``width`` × ``height``
        (the request's centre crop and resize). ValueError: a point outside the crop."""
        x0, y0, x1, y1 = box
        scale = np.array([width / (x1 - x0), height / (y1 - y0)])
        start = self.positions[:, 0]
        outside = ~((start[:, 0] >= x0) & (start[:, 0] < x1) & (start[:, 1] >= y0) & (start[:, 1] < y1))
        if outside.any():
            i = int(np.argmax(outside))
            raise ValueError(f"drag {i + 1} starts at ({start[i, 0]:g}, {start[i, 1]:g}), outside the part of the "
                             f"photograph the model sees (x {x0}–{x1}, y {y0}–{y1}: the centre crop to its aspect "
                             f"ratio)")
        return Drags(self.times, (self.positions - np.array([x0, y0])) * scale, width, height)


def parse_drag(text: str) -> tuple[float, float, float, float, float]:
    """``"X,Y:DX,DY[@T]"`` → (x, y, dx, dy, t): the point (x, y), pixels of the photograph, moves by (dx, dy) pixels
    by normalised time t in (0, 1] (default 1, the clip's end). ValueError: another form, a non-finite number, or t
    outside (0, 1]."""
    m = _DRAG.match(text)
    if m is None:
        raise ValueError(f"--drag {text!r}: expected X,Y:DX,DY or X,Y:DX,DY@T (pixels of the photograph; T in (0, 1], "
                         f"the time the point gets there, default 1)")
    try:
        x, y, dx, dy = (float(v) for v in m.groups()[:4])
        t = 1.0 if m.group(5) is None else float(m.group(5))
    except ValueError:
        raise ValueError(f"--drag {text!r}: X, Y, DX, DY and T must be numbers") from None
    if not all(math.isfinite(v) for v in (x, y, dx, dy, t)):
        raise ValueError(f"--drag {text!r}: X, Y, DX, DY and T must be finite numbers")
    if not 0 < t <= 1:
        raise ValueError(f"--drag {text!r}: T must lie in (0, 1] (normalised clip time), got {t:g}")
    return x, y, dx, dy, t


def drags_from_flags(texts: list[str], width: int, height: int) -> Drags:
    """:class:`Drags` of ``--drag`` texts (:func:`parse_drag`) on a ``width`` × ``height`` photograph: each point
    moves linearly from time 0 to its T and stays. ValueError: as :func:`parse_drag`; a point outside the photograph
    (naming the ``--drag``)."""
    parsed = [parse_drag(text) for text in texts]
    times = np.unique(np.array([0.0, *(t for *_, t in parsed)]))
    positions = np.zeros((len(parsed), len(times), 2))
    for i, (x, y, dx, dy, t) in enumerate(parsed):
        w = np.clip(times / t, 0, 1)[:, None]
        positions[i] = np.array([x, y]) + w * np.array([dx, dy])
    try:
        return Drags(times, positions, width, height)
    except ValueError as e:
        raise ValueError(f"--drag: {e}") from None


def drags_from_tracks(tracks: np.ndarray, width: int, height: int) -> Drags:
    """:class:`Drags` of point tracks (N, T, 2) pixels (x, y) over T ≥ 2 evenly spaced clip times, frame 0 the
    photograph's (the layout TAPIR and CoTracker write). ValueError: another shape, non-finite values, a first point
    outside the photograph."""
    tracks = np.asarray(tracks, dtype=np.float64)
    if tracks.ndim != 3 or tracks.shape[0] < 1 or tracks.shape[1] < 2 or tracks.shape[2] != 2:
        raise ValueError(f"tracks must be (N, T, 2) pixels with N ≥ 1 and T ≥ 2, got {tracks.shape}")
    return Drags(np.linspace(0.0, 1.0, tracks.shape[1]), tracks, width, height)


def drag_segments(image: Tensor, depth: Tensor, *, k: float = SEGMENT_K, depth_weight: float = DEPTH_WEIGHT
                  ) -> np.ndarray:
    """(H, W) int32 region labels of the photograph: Felzenszwalb's graph segmentation (σ :data:`SEGMENT_SIGMA`, k
    ``k``, regions of ≥ 10 pixels) of CIELAB colour and ``depth_weight`` × log depth, at :data:`SEGMENT_HEIGHT` pixels
    of height (area resize), labels resized back (nearest). ``image`` (H, W, 3) in [0, 1]; ``depth`` (H, W) z-depth,
    metres (non-finite or ≤ 0: the largest finite depth)."""
    H, W = image.shape[:2]
    h = min(H, SEGMENT_HEIGHT)
    w = max(1, round(W * h / H))
    rgb = (image.detach().float().clamp(0, 1) * 255).round().to(torch.uint8).cpu().numpy()  # device: OpenCV on host
    z = depth.detach().double().cpu().numpy()  # device: OpenCV segments on the host; labels are host arrays
    ok = np.isfinite(z) & (z > 0)
    z = np.where(ok, z, z[ok].max() if ok.any() else 1.0)
    lab = cv2.cvtColor(cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA), cv2.COLOR_RGB2LAB).astype(np.float32)
    logz = cv2.resize(np.log(z).astype(np.float32), (w, h), interpolation=cv2.INTER_AREA)
    features = np.concatenate([lab, depth_weight * logz[..., None]], axis=-1)
    segmenter = cv2.ximgproc.segmentation.createGraphSegmentation(sigma=SEGMENT_SIGMA, k=k, min_size=10)
    labels = segmenter.processImage(features)
    return cv2.resize(labels, (W, H), interpolation=cv2.INTER_NEAREST)


def support_normal(depth: np.ndarray, Kinv: np.ndarray, *, iterations: int = 256, seed: int = 0) -> np.ndarray | None:
    """The unit normal, pointing up, of the surface the scene rests on, in the camera's frame: the plane of RANSAC
    (Fischler & Bolles 1981) over the back-projected pixels of :data:`SEGMENT_HEIGHT` rows that holds the most points
    within :data:`SUPPORT_INLIER` × the median depth, among planes whose normal is within :data:`SUPPORT_TILT_DEG` of
    the camera's up (−y), then refitted to its inliers by least squares.

    Args:
        depth: (H, W) z-depth, metres (non-finite or ≤ 0: no point). Kinv: (3, 3) inverse intrinsics, pixels.
        iterations: RANSAC's samples; seed: its generator's (the result is the same for the same input).

    Returns:
        (3,) float64 with n·(0, −1, 0) > 0, or None: fewer than :data:`SUPPORT_MIN_FRACTION` of the points on any
        such plane, or its inliers a band rather than a surface (:data:`SUPPORT_SPREAD`): no floor, table or ground
        in view.
    """
    H, W = depth.shape
    step = max(1, H // SEGMENT_HEIGHT)
    rows, cols = np.mgrid[0:H:step, 0:W:step]
    z = depth[rows, cols]
    valid = np.isfinite(z) & (z > 0)
    if valid.sum() < 3:
        return None
    pix = np.stack([cols[valid] + 0.5, rows[valid] + 0.5, np.ones(int(valid.sum()))], axis=1)
    points = (pix @ Kinv.T) * z[valid][:, None]  # (P, 3) metres
    tol, up = SUPPORT_INLIER * float(np.median(z[valid])), np.array([0.0, -1.0, 0.0])
    cos_tilt = math.cos(math.radians(SUPPORT_TILT_DEG))
    rng = np.random.default_rng(seed)
    best, best_count = None, int(SUPPORT_MIN_FRACTION * len(points))
    for _ in range(iterations):
        a, b, c = points[rng.choice(len(points), 3, replace=False)]
        n = np.cross(b - a, c - a)
        norm = np.linalg.norm(n)
        if norm < 1e-12:
            continue
        n = n / norm * (1.0 if n @ up >= 0 else -1.0)
        if n @ up < cos_tilt:
            continue
        inliers = np.abs((points - a) @ n) < tol
        if inliers.sum() > best_count:
            best, best_count = inliers, int(inliers.sum())
    if best is None:
        return None
    on = points[best]
    _, spread, vt = np.linalg.svd(on - on.mean(axis=0), full_matrices=False)  # vt[2]: the least-variance direction
    if spread[1] < SUPPORT_SPREAD * spread[0]:
        return None  # a band (a wall's row of pixels and what else lies near it), not a surface
    n = vt[2]
    return n * (1.0 if n @ up >= 0 else -1.0)


def drag_motion(drags: Drags, image: Tensor, depth: Tensor, K: Tensor, times: Tensor,
                segments: np.ndarray | None = None) -> tuple[Tensor, Tensor]:
    """Dense motion of the photograph's pixels (module docstring).

    Args:
        drags: at ``image``'s size (:meth:`Drags.resized`).
        image: (H, W, 3) in [0, 1]; depth: (H, W) z-depth, metres; K: (3, 3) pixels, the photograph's camera.
        times: (Kt,) normalised clip times in [0, 1] to give the motion at.
        segments: (H, W) region labels (default :func:`drag_segments`).

    Returns:
        (motion (Kt, H, W, 3) metres in the camera's frame, moving (H, W) bool: the dragged regions), float32 on
        ``image``'s device.
    """
    H, W = image.shape[:2]
    labels = drag_segments(image, depth) if segments is None else segments
    z = depth.detach().double().cpu().numpy()  # device: the dense maps are built on the host, moved back below
    Kinv = np.linalg.inv(K.detach().double().cpu().numpy())  # device: a 3×3 on the host, beside the maps
    normal = support_normal(z, Kinv)
    start = drags.positions[:, 0]
    cols = np.clip(start[:, 0].astype(int), 0, W - 1)
    rows = np.clip(start[:, 1].astype(int), 0, H - 1)
    moving = np.isin(labels, labels[rows, cols])
    # each moving pixel follows the nearest drag of its own region
    yy, xx = np.nonzero(moving)
    distance = (xx[:, None] + 0.5 - start[None, :, 0]) ** 2 + (yy[:, None] + 0.5 - start[None, :, 1]) ** 2
    distance[labels[yy, xx][:, None] != labels[rows, cols][None, :]] = np.inf
    nearest = np.argmin(distance, axis=1)
    zd = np.where(np.isfinite(z[rows, cols]) & (z[rows, cols] > 0), z[rows, cols], 1.0)  # (N,)
    ones = np.ones((len(drags), 1))
    points = (np.concatenate([start, ones], axis=1) @ Kinv.T) * zd[:, None]  # (N, 3) the dragged points
    out = np.zeros((len(times), H, W, 3))
    for k, t in enumerate(times.detach().double().cpu().tolist()):
        now = drags.at(t)  # (N, 2)
        flat = (np.concatenate([now - start, 0 * ones], axis=1) @ Kinv.T) * zd[:, None]  # constant-depth lift
        motion = flat
        if normal is not None:
            rays = np.concatenate([now, ones], axis=1) @ Kinv.T  # (N, 3) each target pixel's ray, z = 1
            along = rays @ normal
            scale = np.divide(points @ normal, along, out=np.full(len(drags), np.nan), where=np.abs(along) > 1e-9)
            ok = np.isfinite(scale) & (scale > zd / LIFT_RANGE) & (scale < zd * LIFT_RANGE)
            motion = np.where(ok[:, None], rays * np.where(ok, scale, 0.0)[:, None] - points, flat)
        out[k, yy, xx] = motion[nearest]
    dev = image.device
    return torch.from_numpy(out).float().to(dev), torch.from_numpy(moving).to(dev)
