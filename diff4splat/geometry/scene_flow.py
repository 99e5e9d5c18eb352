"""Scene flow of a video's pixels from dense optical flow and depth (docs/DESIGN.md, "Motion measured from frames").

1. :func:`optical_flow`: OpenCV's DIS (Kroeger et al., ECCV 2016) on the frames upsampled ``upsample``×, averaged
   back to the frames' grid.
2. :func:`track_pixels`: frame 0's pixels chained through consecutive flows with the forward-backward check
   (Sundaram et al., ECCV 2010); a lost track keeps its last position.
3. :func:`lift_tracks`: tracked pixels to 3D with each frame's z-depth and camera, at the 3×3 neighbour's depth
   closest to the point's unmoved depth; a pixel within ``gate_px`` of its epipolar segment
   (:data:`RIGID_DEPTH_FACTORS`) is static and keeps its frame-0 position.

Pixel (i, j) is centred at (j + 0.5, i + 0.5); ``viewmats`` world-to-camera, ``Ks`` pixels, z-depths in metres.
OpenCV sees CPU copies; results are on the frames' device.
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
           "chain_flows", "track_pixels", "lift_tracks", "source_frame_motion", "source_motion", "sample_pixels",
           "pixel_centres", "RIGID_DEPTH_FACTORS"]

DIS_PRESETS = {"ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST, "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
               "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM}
"""OpenCV's DIS presets by name (speed against accuracy)."""
FLOW_UPSAMPLE = 4
"""Default factor by which frames are upsampled before DIS."""
FB_TOLERANCE_PX = 0.5
"""Default forward-backward tolerance, pixels of the frames' grid."""
RIGID_DEPTH_FACTORS = (0.25, 0.35, 0.5, 0.71, 1.0, 1.41, 2.0, 2.83, 4.0)
"""Depth factors of :func:`lift_tracks`' rigidity test: a pixel is static when within the gate of where the camera's
own motion puts its frame-0 point at any of these multiples of its depth (a depth off by up to 4× stays static)."""
GATE_PX = 2.0
"""Default rigidity gate, pixels: a tracked pixel this close to its camera-motion-only position is static."""


def optical_flow(src: Tensor, dst: Tensor, *, upsample: int = FLOW_UPSAMPLE, preset: str = "medium") -> Tensor:
    """Dense optical flow (OpenCV DIS) from each ``src`` to its ``dst`` frame, (P, 3, H, W) RGB in [0, 1] (clamped),
    computed on frames resized ``upsample``× (bicubic; 1: none) and averaged back; ``preset``: one of
    :data:`DIS_PRESETS`.

    Returns:
        (P, H, W, 2) float32 (du, dv), pixels: pixel (u, v) of ``src[p]`` is at (u + du, v + dv) in ``dst[p]``; on
        ``src``'s device.

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
    rgb = (both.detach().clamp(0, 1) * 255).round().to(torch.uint8).permute(0, 2, 3, 1)
    rgb = rgb.cpu().numpy()  # device: OpenCV reads host arrays (the flow goes back to the frames' device)
    gray = np.stack([cv2.cvtColor(np.ascontiguousarray(x), cv2.COLOR_RGB2GRAY) for x in rgb])  # (2P, uH, uW) uint8
    dis = cv2.DISOpticalFlow_create(DIS_PRESETS[preset])
    P = src.shape[0]
    flows = np.stack([dis.calc(gray[i], gray[P + i], None) for i in range(P)])  # (P, uH, uW, 2)
    flow = torch.from_numpy(flows).to(src.device).permute(0, 3, 1, 2)  # device: OpenCV's CPU result moved
    if up > 1:
        flow = F.avg_pool2d(flow, up) / up
    return flow.permute(0, 2, 3, 1).contiguous()


def sample_pixels(maps: Tensor, uv: Tensor) -> Tensor:
    """Bilinear samples of ``maps`` (P, H, W, C) at pixel positions ``uv`` (P, ..., 2) (centres at +0.5, border values
    outside): (P, ..., C) in ``maps``' dtype."""
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
    """:func:`optical_flow` between consecutive frames (T, 3, H, W), T ≥ 2, both ways: forward (T − 1, H, W, 2), frame t
    → t + 1, and backward (T − 1, H, W, 2), frame t + 1 → t.

    Raises:
        ValueError: ``frames`` not (T, 3, H, W) with T ≥ 2, or as :func:`optical_flow`.
    """
    if frames.dim() != 4 or frames.shape[1] != 3 or frames.shape[0] < 2:
        raise ValueError(f"frames must be (T, 3, H, W) with T ≥ 2, got {tuple(frames.shape)}")
    return (optical_flow(frames[:-1], frames[1:], upsample=upsample, preset=preset),
            optical_flow(frames[1:], frames[:-1], upsample=upsample, preset=preset))


def chain_flows(forward: Tensor, backward: Tensor, *, fb_tolerance: float = FB_TOLERANCE_PX,
                unchecked: int = 0) -> tuple[Tensor, Tensor]:
    """Follow every pixel of the first frame through a sequence: ``forward[k]`` maps frame k to k + 1, ``backward[k]``
    frame k + 1 to k, each (T − 1, H, W, 2) pixels; ``fb_tolerance`` > 0 pixels (``inf`` keeps every track), checked
    from link ``unchecked`` ≥ 0 on (the first ``unchecked`` links are followed whatever their forward-backward error).

    Returns:
        positions (T, H, W, 2) pixels (frame 0: the centres); tracked (T, H, W) bool, False from the step the track
        was lost (its position is then held: at the last position that passed the check, so a track that fails an
        unchecked link is shown moved at that link and held at its start after it).

    Raises:
        ValueError: flows of different or wrong shapes, ``fb_tolerance`` not > 0, ``unchecked`` < 0.
    """
    if forward.dim() != 4 or forward.shape[-1] != 2 or forward.shape != backward.shape:
        raise ValueError(f"forward and backward must both be (T − 1, H, W, 2), got {tuple(forward.shape)} and "
                         f"{tuple(backward.shape)}")
    if not float(fb_tolerance) > 0:
        raise ValueError(f"fb_tolerance must be > 0 pixels, got {fb_tolerance}")
    if unchecked < 0:
        raise ValueError(f"unchecked must be ≥ 0 links, got {unchecked}")
    _, H, W, _ = forward.shape
    uv = pixel_centres(H, W, forward)  # (H, W, 2) where each track is, held where it was lost
    alive = torch.ones(H, W, dtype=torch.bool, device=forward.device)
    positions, tracked = [uv], [alive]
    for k in range(forward.shape[0]):
        step = sample_pixels(forward[k:k + 1], uv[None])[0]
        moved = uv + step
        back = sample_pixels(backward[k:k + 1], moved[None])[0]
        inside = alive & (moved[..., 0] >= 0) & (moved[..., 0] <= W) & (moved[..., 1] >= 0) & (moved[..., 1] <= H)
        alive = inside & ((step + back).norm(dim=-1) <= fb_tolerance)
        shown = inside if k < unchecked else alive  # an unchecked link is followed, later links go on from the check
        positions.append(torch.where(shown[..., None], moved, uv))
        tracked.append(shown)
        uv = torch.where(alive[..., None], moved, uv)
    return torch.stack(positions), torch.stack(tracked)


def track_pixels(frames: Tensor, *, upsample: int = FLOW_UPSAMPLE, fb_tolerance: float = FB_TOLERANCE_PX,
                 preset: str = "medium") -> tuple[Tensor, Tensor]:
    """Follow every pixel of frame 0 through ``frames`` (T, 3, H, W), T ≥ 1: :func:`consecutive_flows` then
    :func:`chain_flows`; ``upsample`` and ``preset`` as :func:`optical_flow`.

    Returns:
        positions (T, H, W, 2) float32 and tracked (T, H, W) bool, as :func:`chain_flows`.

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
    """(F, H, W, 2) pixels of the frame-0 points (H, W, 3) unmoved, at each :data:`RIGID_DEPTH_FACTORS` distance."""
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
    """Of the 3×3 pixels of ``depth`` (H, W) around each position ``uv`` (H, W, 2), the one closest to ``expected``."""
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
    """3D positions of frame 0's tracked pixels (``positions``, ``tracked`` of :func:`track_pixels`) in every frame
    (module docstring, step 3). ``depths`` (D, H, W): z-depths, metres, finite and > 0, of the D increasing frames
    ``depth_frames`` from 0 (default: all); other frames lift at the camera-space depth interpolated linearly in frame
    index. ``Ks`` (T, 3, 3) pixels, ``viewmats`` (T, 4, 4); ``gate_px`` ≥ 0 pixels.

    Returns:
        points (T, H, W, 3) world positions, metres; moving (T, H, W) bool, off the frame-0 position at frame t.

    Raises:
        ValueError: shapes that do not match, ``depth_frames`` not increasing from 0 within [0, T), a depth that is
            not finite and > 0, ``gate_px`` < 0.
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


def _check_sources(sources: list[int], num_frames: int, depths_shape: tuple, height: int, width: int) -> list[int]:
    """``sources`` as ints, if they increase within [0, ``num_frames``) and ``depths_shape`` is (S, ``height``,
    ``width``).

    Raises:
        ValueError: naming both.
    """
    sources = [int(f) for f in sources]
    if tuple(depths_shape) != (len(sources), height, width) or any(b <= a for a, b in pairwise(sources)) \
            or not sources or sources[0] < 0 or sources[-1] >= num_frames:
        raise ValueError(f"depths {tuple(depths_shape)} must be (S, {height}, {width}) for S increasing sources within "
                         f"[0, {num_frames}), got sources {sources}")
    return sources


def source_motion(flows: tuple[Tensor, Tensor], depths: Tensor, sources: list[int], s: int, Ks: Tensor,
                  viewmats: Tensor, span: tuple[int, int], *, fb_tolerance: float = FB_TOLERANCE_PX,
                  gate_px: float = GATE_PX, unchecked: int = 0) -> Tensor:
    """(hi − lo + 1, H, W, 3) displacement Δμ, metres, world frame, of source ``s``'s pixels (frame ``sources[s]``) at
    frames ``span`` = (lo, hi) (:func:`_check_spans`): :func:`source_frame_motion` of one source over part of the
    clip. Tracking is causal in each direction and the span ends on source frames or the clip's ends, so every frame
    of the span gets exactly what the whole clip's tracking gives it. ``flows``: the clip's
    :func:`consecutive_flows`; the other arguments as :func:`source_frame_motion` (checked there)."""
    f = sources[s]
    lo, hi = span
    fw, bw = flows
    H, W = depths.shape[-2:]
    out = depths.new_zeros(hi - lo + 1, H, W, 3, dtype=torch.promote_types(depths.dtype, torch.float32))
    for order, forward, backward in ((list(range(f, hi + 1)), fw[f:hi], bw[f:hi]),  # forward in time from f
                                     (list(range(f, lo - 1, -1)), bw[lo:f].flip(0), fw[lo:f].flip(0))):  # backward
        if len(order) < 2:
            continue
        keys = [i for i, frame in enumerate(order) if frame in sources]
        positions, tracked = chain_flows(forward, backward, fb_tolerance=fb_tolerance, unchecked=unchecked)
        points, _ = lift_tracks(positions, tracked, depths[[sources.index(order[i]) for i in keys]],
                                Ks[order], viewmats[order], depth_frames=keys, gate_px=gate_px)
        out[[frame - lo for frame in order]] = (points - points[:1]).to(out.dtype)
    return out


def _check_spans(spans: list[tuple[int, int]] | None, sources: list[int], num_frames: int) -> list[tuple[int, int]]:
    """Each source's (first, last) tracked frame: ``spans`` if every one is a pair of ints with 0 ≤ first ≤ source ≤
    last < ``num_frames``, each a source frame or an end of the clip (where the depth between source frames is
    interpolated, :func:`lift_tracks`, both of its ends are then in the span), one per source; None: the whole clip
    for each. Else ValueError."""
    if spans is None:
        return [(0, num_frames - 1)] * len(sources)
    spans = [tuple(x) for x in spans]
    if len(spans) != len(sources) or any(len(x) != 2 or not all(isinstance(v, int) for v in x) for x in spans) \
            or any(not 0 <= lo <= f <= hi < num_frames for (lo, hi), f in zip(spans, sources, strict=True)) \
            or any(end not in sources and end not in (0, num_frames - 1) for span in spans for end in span):
        raise ValueError(f"spans must be one (first, last) frame pair per source with 0 <= first <= source <= last < "
                         f"{num_frames}, each a source frame or an end of the clip, got {spans} for sources {sources}")
    return spans


def source_frame_motion(frames: Tensor, depths: Tensor, sources: list[int], Ks: Tensor, viewmats: Tensor, *,
                        upsample: int = FLOW_UPSAMPLE, fb_tolerance: float = FB_TOLERANCE_PX,
                        gate_px: float = GATE_PX, flows: tuple[Tensor, Tensor] | None = None,
                        unchecked: int = 0, spans: list[tuple[int, int]] | None = None) -> Tensor:
    """(T, S, H, W, 3) displacement Δμ(t), metres, world frame, of each source frame's pixels from their position at
    their own frame ``sources[s]`` (S increasing indices in [0, T)): tracked both ways (:func:`chain_flows` over the
    video's :func:`consecutive_flows`, ``flows`` when given) and lifted with the source frames' ``depths`` (S, H, W)
    (:func:`lift_tracks`). ``frames`` (T, 3, H, W) RGB in [0, 1]; ``Ks``, ``viewmats`` (T, 3, 3), (T, 4, 4);
    ``unchecked``: as :func:`chain_flows`, in each direction; ``spans``: per source the (first, last) frame it is
    tracked to (:func:`_check_spans`; None: the whole clip), zero outside (:func:`source_motion`).

    Raises:
        ValueError: ``depths`` not (S, H, W), sources not increasing within [0, T), bad ``spans``, or as
            :func:`chain_flows` and :func:`lift_tracks`.
    """
    T, _, H, W = frames.shape
    sources = _check_sources(sources, T, depths.shape, H, W)
    spans = _check_spans(spans, sources, T)
    out = depths.new_zeros(T, len(sources), H, W, 3, dtype=torch.promote_types(depths.dtype, torch.float32))
    if T < 2:
        return out
    flows = consecutive_flows(frames, upsample=upsample) if flows is None else flows
    for s, (lo, hi) in enumerate(spans):
        out[lo:hi + 1, s] = source_motion(flows, depths, sources, s, Ks, viewmats, (lo, hi),
                                          fb_tolerance=fb_tolerance, gate_px=gate_px, unchecked=unchecked)
    return out
