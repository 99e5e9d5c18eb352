"""Scene flow of a video's pixels from dense optical flow and depth: the classical motion front end.

Where a pixel of frame 0 is at every later frame, in 3D (DGS-LRM and MoVieS supervise and predict the same
quantity with networks; here it is measured from the frames):

1. :func:`optical_flow`: dense 2D flow between frames by OpenCV's DIS (Kroeger et al., ECCV 2016,
   ``cv2.DISOpticalFlow``) on the frames upsampled ``upsample``× (DIS matches 8×8 patches at its finest scale, too
   coarse for a 64² frame), averaged back to the frames' grid.
2. :func:`track_pixels`: every pixel of frame 0 followed through the frames by chaining the flow of consecutive
   frames (each step is small, where DIS is reliable; the flow 0 → t of one call fails on large motions), with
   the forward-backward check (Sundaram et al., ECCV 2010): a step whose backward flow does not bring the pixel
   back within ``fb_tolerance`` pixels, or that leaves the image, loses the track, and a lost track keeps its last
   position.
3. :func:`lift_tracks`: the tracked pixels to 3D with each frame's z-depth map and camera. The depth at a tracked
   pixel is the one of its 3×3 neighbourhood closest to the depth the point would have if it had not moved
   (a pixel's depth at an object's edge is often the background's); a point whose tracked pixel lies within
   ``gate_px`` of where the camera's own motion puts it (the rigidity test of motion segmentation) is static and
   keeps its frame-0 position, so a static scene comes out static whatever the depth's noise.

Conventions as everywhere (docs/DESIGN.md, "Conventions"): pixel (i, j) has its centre at (j + 0.5, i + 0.5);
``viewmats`` world-to-camera, ``Ks`` in pixels, depths are z-depths in metres. OpenCV sees CPU copies; every
result is on the frames' device.
"""
from __future__ import annotations

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from kornia.geometry.camera import project_points, unproject_points
from kornia.geometry.linalg import transform_points
from torch import Tensor

from .cameras import invert_rigid
from .checks import check_positive_int

__all__ = ["DIS_PRESETS", "FLOW_UPSAMPLE", "FB_TOLERANCE_PX", "GATE_PX", "optical_flow", "track_pixels",
           "lift_tracks", "sample_pixels"]

DIS_PRESETS = {"ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST, "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
               "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM}
"""OpenCV's DIS presets by name (speed against accuracy)."""
FLOW_UPSAMPLE = 4
"""Default factor by which frames are upsampled before DIS (module docstring, step 1)."""
FB_TOLERANCE_PX = 0.5
"""Default forward-backward tolerance, pixels of the frames' grid (module docstring, step 2)."""
GATE_PX = 2.0
"""Default rigidity gate, pixels: a tracked pixel this close to its camera-motion-only position is static
(docs/benchmarks.md, "Scene flow from optical flow": 1 px let 2.6 mm of spurious motion into static clips)."""


def _gray_uint8(frames: Tensor) -> np.ndarray:  # (P, 3, H, W) in [0, 1] → (P, H, W) uint8
    rgb = (frames.detach().clamp(0, 1) * 255).round().to(torch.uint8).permute(0, 2, 3, 1).cpu().numpy()
    return np.stack([cv2.cvtColor(np.ascontiguousarray(x), cv2.COLOR_RGB2GRAY) for x in rgb])


def optical_flow(src: Tensor, dst: Tensor, *, upsample: int = FLOW_UPSAMPLE, preset: str = "medium") -> Tensor:
    """Dense optical flow from each ``src`` frame to its ``dst`` frame (OpenCV DIS, module docstring step 1).

    Args:
        src, dst: (P, 3, H, W) RGB in [0, 1] (values outside are clamped), any device.
        upsample: frames are resized by this integer factor (bicubic) before DIS; the flow is averaged back to
            (H, W) and divided by it. 1 runs DIS on the frames themselves.
        preset: one of :data:`DIS_PRESETS`.

    Returns:
        (P, H, W, 2) float32 displacement (du, dv) in pixels of the (H, W) grid: the pixel centred at (u, v) of
        ``src[p]`` is at (u + du, v + dv) in ``dst[p]``. On ``src``'s device.

    Raises:
        ValueError: ``src``/``dst`` not the same (P, 3, H, W) shape, an unknown preset, ``upsample`` < 1.
    """
    if src.dim() != 4 or src.shape[1] != 3 or src.shape != dst.shape:
        raise ValueError(f"src and dst must both be (P, 3, H, W), got {tuple(src.shape)} and {tuple(dst.shape)}")
    if preset not in DIS_PRESETS:
        raise ValueError(f"preset must be one of {sorted(DIS_PRESETS)}, got {preset!r}")
    up = check_positive_int("upsample", upsample)
    both = torch.cat([src, dst]).float()
    if up > 1:
        both = F.interpolate(both, scale_factor=up, mode="bicubic", align_corners=False)
    gray = _gray_uint8(both)
    dis = cv2.DISOpticalFlow_create(DIS_PRESETS[preset])
    P = src.shape[0]
    flows = np.stack([dis.calc(gray[i], gray[P + i], None) for i in range(P)])  # (P, uH, uW, 2)
    flow = torch.from_numpy(flows).to(src.device).permute(0, 3, 1, 2)  # device: OpenCV's CPU result moved
    if up > 1:
        flow = F.avg_pool2d(flow, up) / up
    return flow.permute(0, 2, 3, 1).contiguous()


def sample_pixels(maps: Tensor, uv: Tensor) -> Tensor:
    """Bilinear samples of per-pixel maps at continuous pixel positions (centres at +0.5; border values outside).

    Args:
        maps: (P, H, W, C).  uv: (P, ..., 2) pixel positions (u right, v down).

    Returns:
        (P, ..., C) in ``maps``' dtype.
    """
    P, H, W, C = maps.shape
    lead = uv.shape[1:-1]
    grid = torch.stack([uv[..., 0] / W * 2 - 1, uv[..., 1] / H * 2 - 1], dim=-1).reshape(P, 1, -1, 2)
    out = F.grid_sample(maps.permute(0, 3, 1, 2), grid.to(maps.dtype), mode="bilinear", padding_mode="border",
                        align_corners=False)  # (P, C, 1, n)
    return out[:, :, 0].transpose(1, 2).reshape(P, *lead, C)


def pixel_centres(height: int, width: int, like: Tensor) -> Tensor:
    """(H, W, 2) pixel centres (j + 0.5, i + 0.5) in ``like``'s dtype and device."""
    v, u = torch.meshgrid(torch.arange(height, dtype=like.dtype, device=like.device) + 0.5,
                          torch.arange(width, dtype=like.dtype, device=like.device) + 0.5, indexing="ij")
    return torch.stack([u, v], dim=-1)


def track_pixels(frames: Tensor, *, upsample: int = FLOW_UPSAMPLE, fb_tolerance: float = FB_TOLERANCE_PX,
                 preset: str = "medium") -> tuple[Tensor, Tensor]:
    """Follow every pixel of frame 0 through the frames (module docstring, step 2).

    Args:
        frames: (T, 3, H, W) RGB in [0, 1], T ≥ 1, any device.
        upsample, preset: as :func:`optical_flow`.
        fb_tolerance: forward-backward tolerance, pixels (> 0; ``inf`` keeps every track).

    Returns:
        positions: (T, H, W, 2) float32 pixel positions of frame 0's pixels in each frame (frame 0: the centres).
        tracked: (T, H, W) bool, False from the step at which the track was lost (its position is then held).

    Raises:
        ValueError: ``frames`` not (T, 3, H, W), ``fb_tolerance`` not > 0, or as :func:`optical_flow`.
    """
    if frames.dim() != 4 or frames.shape[1] != 3 or frames.shape[0] < 1:
        raise ValueError(f"frames must be (T, 3, H, W) with T ≥ 1, got {tuple(frames.shape)}")
    if not float(fb_tolerance) > 0:
        raise ValueError(f"fb_tolerance must be > 0 pixels, got {fb_tolerance}")
    T, _, H, W = frames.shape
    uv = pixel_centres(H, W, frames.float())
    positions, tracked = [uv], [torch.ones(H, W, dtype=torch.bool, device=frames.device)]
    if T > 1:
        fw = optical_flow(frames[:-1], frames[1:], upsample=upsample, preset=preset)  # (T-1, H, W, 2)
        bw = optical_flow(frames[1:], frames[:-1], upsample=upsample, preset=preset)
    for t in range(1, T):
        step = sample_pixels(fw[t - 1:t], uv[None])[0]
        moved = uv + step
        back = sample_pixels(bw[t - 1:t], moved[None])[0]
        inside = (moved[..., 0] >= 0) & (moved[..., 0] <= W) & (moved[..., 1] >= 0) & (moved[..., 1] <= H)
        ok = tracked[-1] & inside & ((step + back).norm(dim=-1) <= fb_tolerance)
        uv = torch.where(ok[..., None], moved, uv)
        positions.append(uv)
        tracked.append(ok)
    return torch.stack(positions), torch.stack(tracked)


def _nearest_depth(depth: Tensor, uv: Tensor, expected: Tensor) -> Tensor:
    """Of the 3×3 pixels around each position, the z-depth closest to ``expected``: depth (H, W), uv (H, W, 2),
    expected (H, W) → (H, W)."""
    H, W = depth.shape
    col = (uv[..., 0] - 0.5).round().long().clamp(0, W - 1)
    row = (uv[..., 1] - 0.5).round().long().clamp(0, H - 1)
    best = depth[row, col]
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            cand = depth[(row + dr).clamp(0, H - 1), (col + dc).clamp(0, W - 1)]
            best = torch.where((cand - expected).abs() < (best - expected).abs(), cand, best)
    return best


def lift_tracks(positions: Tensor, tracked: Tensor, depths: Tensor, Ks: Tensor, viewmats: Tensor, *,
                gate_px: float = GATE_PX) -> tuple[Tensor, Tensor]:
    """3D positions of frame 0's tracked pixels in every frame (module docstring, step 3).

    Args:
        positions, tracked: (T, H, W, 2), (T, H, W) from :func:`track_pixels`.
        depths: (T, H, W) z-depth maps, metres, finite and > 0 (fill invalid pixels before).
        Ks: (T, 3, 3) pixels.  viewmats: (T, 4, 4) world-to-camera.
        gate_px: rigidity gate, pixels (≥ 0; 0 treats every tracked pixel that moved at all as moving).

    Returns:
        points: (T, H, W, 3) world positions, metres (frame 0: the pixels unprojected at ``depths[0]``).
        moving: (T, H, W) bool, the points whose position at frame t is not their frame-0 position.

    Raises:
        ValueError: shapes that do not match, a depth that is not finite and > 0, ``gate_px`` < 0.
    """
    T, H, W = tracked.shape
    if positions.shape != (T, H, W, 2) or depths.shape != (T, H, W) or Ks.shape != (T, 3, 3) \
            or viewmats.shape != (T, 4, 4):
        raise ValueError(f"positions {tuple(positions.shape)}, tracked {tuple(tracked.shape)}, depths "
                         f"{tuple(depths.shape)}, Ks {tuple(Ks.shape)} and viewmats {tuple(viewmats.shape)} must be "
                         "(T, H, W, 2), (T, H, W), (T, H, W), (T, 3, 3), (T, 4, 4)")
    if not bool((torch.isfinite(depths) & (depths > 0)).all()):
        raise ValueError("depths must be finite and > 0 (fill invalid pixels first)")
    if not float(gate_px) >= 0:
        raise ValueError(f"gate_px must be ≥ 0, got {gate_px}")
    dtype = torch.promote_types(depths.dtype, torch.float32)
    uv, depths, Ks, viewmats = positions.to(dtype), depths.to(dtype), Ks.to(dtype), viewmats.to(dtype)
    cam_to_world = invert_rigid(viewmats)
    first = transform_points(cam_to_world[:1], unproject_points(uv[0].reshape(1, -1, 2), depths[0].reshape(1, -1, 1),
                                                                Ks[:1]))[0].reshape(H, W, 3)
    points, moving = [first], [torch.zeros(H, W, dtype=torch.bool, device=depths.device)]
    for t in range(1, T):
        still_cam = transform_points(viewmats[t:t + 1], points[-1].reshape(1, -1, 3))[0].reshape(H, W, 3)
        z = _nearest_depth(depths[t], uv[t], still_cam[..., 2])
        lifted = transform_points(cam_to_world[t:t + 1], unproject_points(uv[t].reshape(1, -1, 2),
                                                                          z.reshape(1, -1, 1), Ks[t:t + 1]))[0]
        ego = project_points(transform_points(viewmats[t:t + 1], first.reshape(1, -1, 3))[0], Ks[t])
        off = (ego.reshape(H, W, 2) - uv[t]).norm(dim=-1) > gate_px
        now = torch.where(tracked[t], off, moving[-1])  # a lost track keeps its last state and position
        point = torch.where(tracked[t][..., None], lifted.reshape(H, W, 3), points[-1])
        points.append(torch.where(now[..., None], point, first))
        moving.append(now)
    return torch.stack(points), torch.stack(moving)
