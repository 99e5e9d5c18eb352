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
   ``gate_px`` of where the camera's own motion puts it at some depth between a quarter and four times the given one
   (a segment of its epipolar line: the rigidity test of motion segmentation, :data:`RIGID_DEPTH_FACTORS`) is
   static and keeps its frame-0 position, so a static scene comes out static whatever the depth's noise.

Conventions as everywhere (docs/DESIGN.md, "Conventions"): pixel (i, j) has its centre at (j + 0.5, i + 0.5);
``viewmats`` world-to-camera, ``Ks`` in pixels, depths are z-depths in metres. OpenCV sees CPU copies; every
result is on the frames' device.
"""
from __future__ import annotations

from itertools import pairwise

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from kornia.geometry.camera import project_points, unproject_points
from kornia.geometry.linalg import transform_points
from torch import Tensor

from diff4splat.cameras import invert_rigid
from diff4splat.utils.checks import check_positive_int

__all__ = ["DIS_PRESETS", "FLOW_UPSAMPLE", "FB_TOLERANCE_PX", "GATE_PX", "optical_flow", "consecutive_flows",
           "chain_flows", "track_pixels", "lift_tracks", "source_frame_motion", "sample_pixels", "pixel_centres",
           "RIGID_DEPTH_FACTORS"]

DIS_PRESETS = {"ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST, "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
               "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM}
"""OpenCV's DIS presets by name (speed against accuracy)."""
FLOW_UPSAMPLE = 4
"""Default factor by which frames are upsampled before DIS (module docstring, step 1)."""
FB_TOLERANCE_PX = 0.5
"""Default forward-backward tolerance, pixels of the frames' grid (module docstring, step 2)."""
RIGID_DEPTH_FACTORS = (0.25, 0.35, 0.5, 0.71, 1.0, 1.41, 2.0, 2.83, 4.0)
"""Depth factors of the rigidity test (:func:`lift_tracks`): a tracked pixel is static when it lies within the gate
of where the camera's own motion puts its frame-0 point at some depth between a quarter and four times the given
one (along the epipolar line), so a depth map off by up to 4× does not make a moving camera's static world move."""
GATE_PX = 2.0
"""Default rigidity gate, pixels: a tracked pixel this close to its camera-motion-only position is static
(docs/benchmarks.md, "Scene flow from optical flow": 1 px let 2.6 mm of spurious motion into static clips)."""


def _gray_uint8(frames: Tensor) -> np.ndarray:  # (P, 3, H, W) in [0, 1] → (P, H, W) uint8
    rgb = (frames.detach().clamp(0, 1) * 255).round().to(torch.uint8).permute(0, 2, 3, 1)
    rgb = rgb.cpu().numpy()  # device: OpenCV reads host arrays (the flow goes back to the frames' device)
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


def consecutive_flows(frames: Tensor, *, upsample: int = FLOW_UPSAMPLE, preset: str = "medium"
                      ) -> tuple[Tensor, Tensor]:
    """The optical flows between consecutive frames, both ways (:func:`optical_flow`): what :func:`chain_flows`
    follows pixels through, computed once for a video.

    Args:
        frames: (T, 3, H, W) RGB in [0, 1], T ≥ 2.

    Returns:
        forward (T − 1, H, W, 2): frame t → t + 1 at t; backward (T − 1, H, W, 2): frame t + 1 → t at t.

    Raises:
        ValueError: ``frames`` not (T, 3, H, W) with T ≥ 2, or as :func:`optical_flow`.
    """
    if frames.dim() != 4 or frames.shape[1] != 3 or frames.shape[0] < 2:
        raise ValueError(f"frames must be (T, 3, H, W) with T ≥ 2, got {tuple(frames.shape)}")
    return (optical_flow(frames[:-1], frames[1:], upsample=upsample, preset=preset),
            optical_flow(frames[1:], frames[:-1], upsample=upsample, preset=preset))


def chain_flows(forward: Tensor, backward: Tensor, *, fb_tolerance: float = FB_TOLERANCE_PX) -> tuple[Tensor, Tensor]:
    """Follow every pixel of the first frame through a sequence given its consecutive flows (module docstring,
    step 2): ``forward[k]`` maps frame k to k + 1 of the sequence, ``backward[k]`` frame k + 1 to k (for a sequence
    running backwards in time, pass :func:`consecutive_flows`' flows reversed and swapped).

    Args:
        forward, backward: (T − 1, H, W, 2) pixel displacements.
        fb_tolerance: forward-backward tolerance, pixels (> 0; ``inf`` keeps every track).

    Returns:
        positions: (T, H, W, 2) pixel positions of the first frame's pixels in each frame (frame 0: the centres).
        tracked: (T, H, W) bool, False from the step at which the track was lost (its position is then held).

    Raises:
        ValueError: flows of different or wrong shapes, ``fb_tolerance`` not > 0.
    """
    if forward.dim() != 4 or forward.shape[-1] != 2 or forward.shape != backward.shape:
        raise ValueError(f"forward and backward must both be (T − 1, H, W, 2), got {tuple(forward.shape)} and "
                         f"{tuple(backward.shape)}")
    if not float(fb_tolerance) > 0:
        raise ValueError(f"fb_tolerance must be > 0 pixels, got {fb_tolerance}")
    _, H, W, _ = forward.shape
    uv = pixel_centres(H, W, forward)
    positions, tracked = [uv], [torch.ones(H, W, dtype=torch.bool, device=forward.device)]
    for k in range(forward.shape[0]):
        step = sample_pixels(forward[k:k + 1], uv[None])[0]
        moved = uv + step
        back = sample_pixels(backward[k:k + 1], moved[None])[0]
        inside = (moved[..., 0] >= 0) & (moved[..., 0] <= W) & (moved[..., 1] >= 0) & (moved[..., 1] <= H)
        ok = tracked[-1] & inside & ((step + back).norm(dim=-1) <= fb_tolerance)
        uv = torch.where(ok[..., None], moved, uv)
        positions.append(uv)
        tracked.append(ok)
    return torch.stack(positions), torch.stack(tracked)


def track_pixels(frames: Tensor, *, upsample: int = FLOW_UPSAMPLE, fb_tolerance: float = FB_TOLERANCE_PX,
                 preset: str = "medium") -> tuple[Tensor, Tensor]:
    """Follow every pixel of frame 0 through the frames: :func:`consecutive_flows` then :func:`chain_flows`.

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
    if frames.shape[0] == 1:
        H, W = frames.shape[-2:]
        return (pixel_centres(H, W, frames.float())[None],
                torch.ones(1, H, W, dtype=torch.bool, device=frames.device))
    return chain_flows(*consecutive_flows(frames, upsample=upsample, preset=preset), fb_tolerance=fb_tolerance)


def _static_segment(points: Tensor, origin: Tensor, viewmat: Tensor, K: Tensor) -> Tensor:
    """Where camera (``viewmat``, ``K``) sees the frame-0 points (H, W, 3) if they did not move, for their ray
    distances from the frame-0 camera centre ``origin`` scaled by each of :data:`RIGID_DEPTH_FACTORS`:
    (F, H, W, 2) pixels, a polyline along each point's epipolar line (one point for a camera that only turned)."""
    rays = points - origin
    factors = rays.new_tensor(RIGID_DEPTH_FACTORS)
    candidates = origin + factors[:, None, None, None] * rays  # (F, H, W, 3)
    cam = transform_points(viewmat[None], candidates.reshape(1, -1, 3))[0]
    cam = torch.cat([cam[:, :2], cam[:, 2:].clamp_min(1e-6)], dim=1)  # behind the camera: far off the image
    return project_points(cam, K).reshape(*candidates.shape[:-1], 2)


def _segment_distance(uv: Tensor, polyline: Tensor) -> Tensor:
    """Distance (H, W) of pixel positions (H, W, 2) to per-pixel polylines (F, H, W, 2), pixels."""
    a, b = polyline[:-1], polyline[1:]
    ab = b - a
    w = ((uv - a) * ab).sum(-1) / (ab * ab).sum(-1).clamp_min(1e-12)
    nearest = a + w.clamp(0, 1)[..., None] * ab
    return (uv - nearest).norm(dim=-1).min(dim=0).values


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
                depth_frames: list[int] | None = None, gate_px: float = GATE_PX) -> tuple[Tensor, Tensor]:
    """3D positions of frame 0's tracked pixels in every frame (module docstring, step 3).

    A frame with a depth map lifts its tracked pixel at the depth of the 3×3 neighbourhood closest to where the
    point would be had it not moved since the previous frame with a depth map; a frame without one (a network
    that predicts depth for some frames only) lifts it at the camera-space depth interpolated linearly, in frame
    index, between the point's depths at the frames with maps around it (the nearest one beyond the last).

    Args:
        positions, tracked: (T, H, W, 2), (T, H, W) from :func:`track_pixels`.
        depths: (D, H, W) z-depth maps of the frames ``depth_frames``, metres, finite and > 0 (fill invalid
            pixels before).
        Ks: (T, 3, 3) pixels.  viewmats: (T, 4, 4) world-to-camera.
        depth_frames: D increasing frame indices, the first 0 (default: every frame, D = T).
        gate_px: rigidity gate, pixels (≥ 0; 0 treats every tracked pixel off its epipolar segment as moving).

    Returns:
        points: (T, H, W, 3) world positions, metres (frame 0: the pixels unprojected at ``depths[0]``).
        moving: (T, H, W) bool, the points whose position at frame t is not their frame-0 position.

    Raises:
        ValueError: shapes that do not match, ``depth_frames`` not increasing from 0 within [0, T), a depth that
            is not finite and > 0, ``gate_px`` < 0.
    """
    T, H, W = tracked.shape
    frames = list(range(T)) if depth_frames is None else [int(f) for f in depth_frames]
    if positions.shape != (T, H, W, 2) or depths.shape != (len(frames), H, W) or Ks.shape != (T, 3, 3) \
            or viewmats.shape != (T, 4, 4):
        raise ValueError(f"positions {tuple(positions.shape)}, tracked {tuple(tracked.shape)}, depths "
                         f"{tuple(depths.shape)}, Ks {tuple(Ks.shape)} and viewmats {tuple(viewmats.shape)} must be "
                         "(T, H, W, 2), (T, H, W), (D, H, W) with D depth frames, (T, 3, 3), (T, 4, 4)")
    if not frames or frames[0] != 0 or any(b <= a for a, b in pairwise(frames)) or frames[-1] >= T:
        raise ValueError(f"depth_frames must increase from 0 and lie below T = {T}, got {frames}")
    if not bool((torch.isfinite(depths) & (depths > 0)).all()):
        raise ValueError("depths must be finite and > 0 (fill invalid pixels first)")
    if not float(gate_px) >= 0:
        raise ValueError(f"gate_px must be ≥ 0, got {gate_px}")
    dtype = torch.promote_types(depths.dtype, torch.float32)
    uv, depths, Ks, viewmats = positions.to(dtype), depths.to(dtype), Ks.to(dtype), viewmats.to(dtype)
    cam_to_world = invert_rigid(viewmats)

    def unproject(t: int, z: Tensor) -> Tensor:  # frame t's tracked pixels at camera-space depths z (H, W)
        cam = unproject_points(uv[t].reshape(1, -1, 2), z.reshape(1, -1, 1), Ks[t:t + 1])
        return transform_points(cam_to_world[t:t + 1], cam)[0].reshape(H, W, 3)

    def camera_z(t: int, points: Tensor) -> Tensor:  # (H, W) z of world points in camera t
        return transform_points(viewmats[t:t + 1], points.reshape(1, -1, 3))[0, :, 2].reshape(H, W)

    first = unproject(0, depths[0])
    origin = cam_to_world[0, :3, 3]
    moving = [torch.zeros(H, W, dtype=torch.bool, device=depths.device)]
    for t in range(1, T):  # the rigidity test needs no depth at t: where the camera alone can put the frame-0 point
        ego = _static_segment(first, origin, viewmats[t], Ks[t])  # (RIGID_DEPTHS, H, W, 2)
        off = _segment_distance(uv[t], ego) > gate_px
        moving.append(torch.where(tracked[t], off, moving[-1]))  # a lost track keeps its last state and position

    def settle(t: int, lifted: Tensor, previous: Tensor) -> Tensor:
        return torch.where(moving[t][..., None], torch.where(tracked[t][..., None], lifted, previous), first)

    # frames with depth maps, in order: each picks its depth near the previous one's point
    at_depth, z_at = {0: first}, {0: depths[0]}
    for k in range(1, len(frames)):
        t, prev = frames[k], at_depth[frames[k - 1]]
        z = _nearest_depth(depths[k], uv[t], camera_z(t, prev))
        at_depth[t] = settle(t, unproject(t, z), prev)
        z_at[t] = camera_z(t, at_depth[t])
    points = [first]
    for t in range(1, T):
        if t in at_depth:
            points.append(at_depth[t])
            continue
        before = max(f for f in frames if f < t)
        after = min((f for f in frames if f > t), default=before)
        w = 0.0 if after == before else (t - before) / (after - before)
        points.append(settle(t, unproject(t, torch.lerp(z_at[before], z_at[after], w)), points[-1]))
    return torch.stack(points), torch.stack(moving)


def source_frame_motion(frames: Tensor, depths: Tensor, sources: list[int], Ks: Tensor, viewmats: Tensor, *,
                        upsample: int = FLOW_UPSAMPLE, fb_tolerance: float = FB_TOLERANCE_PX,
                        gate_px: float = GATE_PX, flows: tuple[Tensor, Tensor] | None = None) -> Tensor:
    """Displacement of every pixel of each source frame at every frame of the video: the scene flow of
    pixel-aligned Gaussians (docs/DESIGN.md, "Data flow of generate", step 6) measured from the frames.

    Source frame s (video frame f = ``sources[s]``) is tracked forward through frames f … T−1 and backward through
    f … 0 (:func:`chain_flows` over the video's :func:`consecutive_flows`, computed once) and lifted
    (:func:`lift_tracks`) with the depth maps of the source frames on each side, which are the only frames with depth.

    Args:
        frames: (T, 3, H, W) RGB in [0, 1].
        depths: (S, H, W) z-depth of the source frames, metres, finite and > 0.
        sources: S video frame indices, increasing, within [0, T).
        Ks, viewmats: (T, 3, 3), (T, 4, 4) the video's cameras.
        upsample, fb_tolerance, gate_px: as :func:`track_pixels` and :func:`lift_tracks`.
        flows: the video's :func:`consecutive_flows` when already computed (``upsample`` is then not used).

    Returns:
        (T, S, H, W, 3) displacement Δμ(t) of each source pixel's point from its position at its own frame,
        metres, world frame; zero at the source's own frame and for every static point.

    Raises:
        ValueError: ``depths`` not (S, H, W) for the S ``sources``, sources not increasing within [0, T), or as
            :func:`chain_flows` and :func:`lift_tracks`.
    """
    T, _, H, W = frames.shape
    sources = [int(f) for f in sources]
    if depths.shape != (len(sources), H, W) or any(b <= a for a, b in pairwise(sources)) \
            or not sources or sources[0] < 0 or sources[-1] >= T:
        raise ValueError(f"depths {tuple(depths.shape)} must be (S, {H}, {W}) for S increasing sources within "
                         f"[0, {T}), got sources {sources}")
    out = depths.new_zeros(T, len(sources), H, W, 3, dtype=torch.promote_types(depths.dtype, torch.float32))
    if T < 2:
        return out
    fw, bw = consecutive_flows(frames, upsample=upsample) if flows is None else flows
    for s, f in enumerate(sources):
        for order, forward, backward in ((list(range(f, T)), fw[f:], bw[f:]),  # forward in time from f
                                         (list(range(f, -1, -1)), bw[:f].flip(0), fw[:f].flip(0))):  # backward
            if len(order) < 2:
                continue
            keys = [i for i, frame in enumerate(order) if frame in sources]
            positions, tracked = chain_flows(forward, backward, fb_tolerance=fb_tolerance)
            points, _ = lift_tracks(positions, tracked, depths[[sources.index(order[i]) for i in keys]],
                                    Ks[order], viewmats[order], depth_frames=keys, gate_px=gate_px)
            out[order, s] = (points - points[:1]).to(out.dtype)
    return out
