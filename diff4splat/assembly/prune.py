"""Pruning of Gaussians: those that never contribute to a camera path, and near-duplicates across the
source frames of a multi-frame reconstruction."""
from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import torch
from torch import Tensor

from diff4splat.cameras.path import CameraPath
from diff4splat.render.projection import project_gaussians
from diff4splat.render.rasterize import rasterize
from diff4splat.render.settings import NEAR_PLANE
from diff4splat.scene.dynamic import DynamicGaussians
from diff4splat.scene.gaussians import Gaussians
from diff4splat.utils.checks import check_finite, check_positive, check_positive_int

__all__ = ["visibility_mask", "prune_scene", "prune_mask", "nothing_seen_message", "duplicate_mask", "occluder_mask",
           "SLIDE_FACTORS", "slide_behind", "settle_generated", "settle_and_prune"]


def visibility_mask(scene: DynamicGaussians, cameras: CameraPath, near_plane: float = NEAR_PLANE) -> Tensor:
    """Which Gaussians any camera of ``cameras`` sees, each at its own frame time.

    A Gaussian is seen by camera i when, deformed to time ``cameras.times[i]``, it passes the
    renderer's culling (:func:`diff4splat.render.project_gaussians`: in front of the near plane and
    its 3σ screen footprint overlapping the image); exactly the Gaussians the rasterizer would skip
    for every frame are reported unseen. With temporal support, a Gaussian gated out at a frame's
    time (:meth:`DynamicGaussians.active_indices`, o·p(t) < 1/255) is not seen by that camera.

    Returns:
        (M,) bool.
    """
    seen = torch.zeros(scene.num_gaussians, dtype=torch.bool, device=scene.canonical.means.device)
    for i in range(len(cameras)):
        t = float(cameras.times[i])
        idx, g = scene.active_indices(t), scene.at(t)
        proj = project_gaussians(g.means, g.quats, g.scales, g.opacities, cameras.viewmats[i:i + 1],
                                 cameras.Ks[i:i + 1], cameras.width, cameras.height, near_plane=near_plane)
        vis = proj.radii[0] > 0
        if idx is None:
            seen |= vis
        else:
            seen[idx[vis]] = True
    return seen


def prune_mask(scene: DynamicGaussians, cameras: CameraPath | None = None, min_opacity: float = 0.005,
               near_plane: float = NEAR_PLANE) -> tuple[Tensor, dict[str, int]]:
    """The Gaussians :func:`prune_scene` keeps, as a mask: opacity ≥ ``min_opacity`` and seen by a camera.

    A Gaussian with opacity o < 1/255 can never pass the 3DGS alpha threshold (alpha ≤ o), so
    ``min_opacity`` ≤ 1/255 prunes only Gaussians that provably never contribute.

    Args:
        scene: the scene.
        cameras: the path the scene will be rendered along, or None to prune by opacity only.
        min_opacity: opacity threshold in [0, 1).

    Returns:
        keep (M,) bool and counts {"before", "low_opacity", "unseen", "after"}.

    Raises:
        ValueError: ``min_opacity`` outside [0, 1).
    """
    if not 0.0 <= min_opacity < 1.0:
        raise ValueError(f"min_opacity must lie in [0, 1), got {min_opacity}")
    opaque = scene.canonical.opacities >= min_opacity
    seen = visibility_mask(scene, cameras, near_plane) if cameras is not None else torch.ones_like(opaque)
    keep = opaque & seen
    stats = {"before": scene.num_gaussians, "low_opacity": int((~opaque).sum()),
             "unseen": int((opaque & ~seen).sum()), "after": int(keep.sum())}
    return keep, stats


def nothing_seen_message(stats: dict[str, int], min_opacity: float) -> str:
    """The error message when pruning left no Gaussian (``stats`` as :func:`prune_mask` returns them), naming the
    likely cause: transparent Gaussians (the model's weights) or cameras that look away from the scene."""
    msg = (f"the camera path sees none of the scene: all {stats['before']} Gaussians were pruned "
           f"({stats['unseen']} outside every camera's view, {stats['low_opacity']} with opacity < {min_opacity})")
    if stats["unseen"] == 0:
        return msg + "; likely cause: the model's weights (every Gaussian is transparent)"
    return msg + ("; likely cause: the cameras look away from the scene (the scene lies in front of the "
                  "first camera, along its +z axis, OpenCV axes)")


def prune_scene(scene: DynamicGaussians, cameras: CameraPath | None = None, min_opacity: float = 0.005,
                near_plane: float = NEAR_PLANE) -> tuple[DynamicGaussians, dict[str, int]]:
    """Drop Gaussians with opacity below ``min_opacity`` or that no camera of ``cameras`` sees (:func:`prune_mask`).

    Returns:
        The pruned scene (deformation arrays follow the kept Gaussians) and the counts of :func:`prune_mask`.

    Raises:
        ValueError: ``min_opacity`` outside [0, 1).
    """
    keep, stats = prune_mask(scene, cameras, min_opacity, near_plane)
    return scene.select(keep), stats


@torch.no_grad()
def duplicate_mask(
    scene: DynamicGaussians,  # M Gaussians (deformation optional)
    source: Tensor,  # (M,) long, source frame index in [0, S)
    viewmats: Tensor,  # (S, 4, 4) world-to-camera of each source frame
    Ks: Tensor,  # (S, 3, 3) pixels
    times: Tensor,  # (S,) clip time of each source frame in [0, 1]
    width: int,
    height: int,
    *,
    min_alpha: float = 0.5,
    depth_tolerance: float = 0.05,
) -> Tensor:
    """Which Gaussians of a later source frame re-describe a surface an earlier source frame already placed.

    Pixel-aligned Gaussians decoded from several source frames (S frames, one H×W grid each) describe
    every surface seen by two frames twice. Source frames are processed in order s = 1 … S−1; for
    frame s, the Gaussians of frames < s that are not already marked duplicate are rendered, deformed
    to ``times[s]`` (:meth:`DynamicGaussians.at`), from camera s (:func:`diff4splat.render.rasterize`,
    "ED") → accumulated alpha A and expected depth D (H, W). A Gaussian of frame s is a duplicate iff
    its mean deformed to ``times[s]``, in camera s's frame (x, y, z) = R·μ + t, lies in front of the
    near plane (z > 0.01 m, :data:`~diff4splat.render.settings.NEAR_PLANE`), projects to
    (u, v) = (fx·x/z + cx, fy·y/z + cy) inside the image, and at pixel (⌊v⌋, ⌊u⌋)
    A ≥ ``min_alpha`` and |z − D| ≤ ``depth_tolerance``·D: the surface is already represented at
    that depth. Gaussians of frame 0 are never duplicates; Gaussians in front of the rendered surface
    (new occluders), behind it, or where A < ``min_alpha`` (content disoccluded or new in frame s)
    are kept. A duplicate of frame s is left out of the renders for the frames after s. With temporal
    support, opacities are o·p(t) at ``times[s]``, as rendered.

    Source: our design for the every-frame decoding of Diff4Splat (Pan et al. 2025, the LDRM's
    "3D deconvolution" decodes Gaussians in "pixel-level correspondence with source video frames";
    the paper does not say how overlapping frames are merged), analogous to the redundancy pruning
    of pixel-aligned feed-forward reconstructions over several key frames. The rule and its
    thresholds are ours (docs/DESIGN.md, "Data flow of generate").

    Args:
        scene: M Gaussians (static or deformed, with or without temporal support), metres.
        source: (M,) integer source-frame index of each Gaussian, in [0, S).
        viewmats: (S, 4, 4) world-to-camera of each source frame (OpenCV frame).
        Ks: (S, 3, 3) pinhole intrinsics of each source frame, pixels.
        times: (S,) clip time of each source frame, in [0, 1].
        width, height: image size of the source cameras, pixels (≥ 1).
        min_alpha: accumulated alpha in (0, 1] above which a pixel counts as covered.
        depth_tolerance: relative depth tolerance (> 0): |z − D| ≤ depth_tolerance·D.

    Returns:
        (M,) bool on the scene's device, True = duplicate (drop).

    Raises:
        ValueError: shapes (source not (M,), viewmats not (S, 4, 4) with S ≥ 1, Ks not (S, 3, 3),
            times not (S,)), a non-integer ``source`` or one outside [0, S), non-finite cameras or
            times, times outside [0, 1], width/height < 1, ``min_alpha`` outside (0, 1],
            ``depth_tolerance`` ≤ 0 or not finite; each message names the argument and its value.
    """
    S = _check_sources(scene, source, viewmats, Ks, times)
    width, height = check_positive_int("width", width, "pixels"), check_positive_int("height", height, "pixels")
    depth_tolerance = _check_thresholds(min_alpha, depth_tolerance)
    means = scene.canonical.means
    viewmats, Ks, source = viewmats.to(means), Ks.to(means), source.to(means.device)
    dup = torch.zeros(scene.num_gaussians, dtype=torch.bool, device=means.device)
    for s in range(1, S):
        cand = torch.nonzero(source == s).squeeze(1)  # (K,)
        earlier = (source < s) & ~dup  # (M,)
        if cand.numel() == 0 or not bool(earlier.any()):
            continue
        need = earlier.clone()
        need[cand] = True
        g = scene.at(float(times[s]), gate=0.0, index=need)  # the earlier and frame s's Gaussians at times[s]
        covered, z, d = _surface_lookup(g.select(earlier[need]), g.means[source[need] == s], viewmats[s], Ks[s],
                                        width, height, min_alpha)
        dup[cand[covered & ((z - d).abs() <= depth_tolerance * d)]] = True
    return dup


@torch.no_grad()
def occluder_mask(
    scene: DynamicGaussians,  # M Gaussians (deformation optional)
    source: Tensor,  # (M,) long, source frame index in [0, S)
    viewmat: Tensor,  # (4, 4) world-to-camera of the input camera (source frame 0)
    K: Tensor,  # (3, 3) pixels
    time: float,  # clip time of the input frame, in [0, 1]
    width: int,
    height: int,
    *,
    min_alpha: float = 0.5,
    depth_tolerance: float = 0.05,
    surface_depth: Tensor | None = None,  # (H, W) z-depth of the photograph's surface, metres
) -> Tensor:  # (M,) bool, True = occludes the photograph (drop)
    """Which Gaussians of later source frames would cover the photograph at the input view.

    The input frame (source 0, the photo layer) is observed: the photograph shows its surface unoccluded at
    ``time``. The Gaussians of source 0 are rendered from the input camera at ``time`` (accumulated alpha A,
    expected depth D). A Gaussian of a later source frame, deformed to ``time``, is tested over its whole screen
    footprint, not only its centre: the renderer's own projection (:func:`diff4splat.render.project_gaussians`)
    gives its centre and 3σ radius; the square of half-width 10/9 of that radius + 1 pixel (the renderer's
    opacity-aware support reaches 3.33σ) around the centre, clipped to the image, is its footprint; a Gaussian
    the projection culls (behind the near plane, footprint outside the image) cannot cover the photograph and is
    kept. If that square holds a pixel
    with A ≥ ``min_alpha`` whose surface the Gaussian's centre is not clearly behind, z < (1 +
    ``depth_tolerance``)·D, it would be composited over (in front) or into (on) the photograph there and is
    dropped: what it describes there, the photograph already shows. Gaussians wholly behind the surface, over
    uncovered pixels, outside the image or behind the camera are kept (what the photograph cannot show:
    disocclusions, the far side). The largest covered D over the square comes from a grey dilation of the depth
    map (:func:`_footprint_max`, squares up to 20 % larger), so the test is conservative. Our rule
    (docs/DESIGN.md, "Data flow of generate"), not the paper's.

    Args:
        scene: M Gaussians (static or deformed), metres.
        source: (M,) integer source-frame index of each Gaussian, in [0, S).
        viewmat: (4, 4) input camera (world-to-camera, OpenCV).  K: (3, 3) its intrinsics, pixels.
        time: clip time of the photograph, in [0, 1].
        width, height: image size, pixels (≥ 1).
        min_alpha: accumulated alpha in (0, 1] above which a pixel counts as covered.
        depth_tolerance: relative depth margin (> 0).
        surface_depth: (H, W) the surface's z-depth at every pixel when it is known exactly (the photo layer's
            depth map, :func:`diff4splat.assembly.assemble.photo_depth`), used instead of rendering source 0 (whose
            expected depth blends neighbouring pixels where the depth varies from pixel to pixel).

    Returns:
        (M,) bool, True = drop; never True for source 0.

    Raises:
        ValueError: the same argument checks as :func:`duplicate_mask` (one camera, ``time`` as its times);
            ``surface_depth`` not (height, width).
    """
    means = scene.canonical.means
    times = torch.tensor([float(time)], dtype=means.dtype, device=means.device)
    _check_sources(scene, torch.zeros_like(source), viewmat[None], K[None], times)
    width, height = check_positive_int("width", width, "pixels"), check_positive_int("height", height, "pixels")
    depth_tolerance = _check_thresholds(min_alpha, depth_tolerance)
    if source.is_floating_point() or source.dtype == torch.bool or (source.numel() and int(source.min()) < 0):
        raise ValueError("source must be a non-negative integer tensor")
    viewmat, K, source = viewmat.to(means), K.to(means), source.to(means.device)
    out = torch.zeros(scene.num_gaussians, dtype=torch.bool, device=means.device)
    cand = torch.nonzero(source > 0).squeeze(1)
    if cand.numel() == 0 or not bool((source == 0).any()):
        return out
    if surface_depth is not None:
        if tuple(surface_depth.shape) != (height, width):
            raise ValueError(f"surface_depth must have shape ({height}, {width}), got {tuple(surface_depth.shape)}")
        depth = surface_depth.to(means)
        c = scene.at(float(time), gate=0.0, index=cand)  # the candidates only: the surface is given
    else:
        g = scene.at(float(time), gate=0.0)
        surface, c = g.select(source == 0), g.select(cand)
        rendered, alpha, _ = rasterize(surface.means, surface.quats, surface.scales, surface.opacities,
                                       surface.opacities[:, None], viewmat[None], K[None], width, height,
                                       render_mode="ED")
        depth = torch.where(alpha[0, ..., 0] >= min_alpha, rendered[0, ..., 0], 0.0)  # (H, W), 0: uncovered
    covers = _covers(c.means, c.quats, c.scales, c.opacities, viewmat, K, width, height, depth, depth_tolerance)
    out[cand[covers]] = True
    return out


def _covers(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, viewmat: Tensor, K: Tensor, width: int,
            height: int, depth: Tensor, depth_tolerance: float) -> Tensor:
    """:func:`occluder_mask`'s test of P Gaussians (positions at the photograph's time) against the surface's
    z-depth ``depth`` (H, W; 0 = uncovered): (P,) bool, True where the footprint square holds a covered pixel whose
    surface the centre is not clearly behind."""
    proj = project_gaussians(means, quats, scales, opacities, viewmat[None], K[None], width, height)
    radii = proj.radii[0].to(depth.dtype)
    d_max = _footprint_max(depth, proj.means2d[0, :, 0], proj.means2d[0, :, 1], radii * (10 / 9) + 1)
    return (radii > 0) & (proj.depths[0] < (1 + depth_tolerance) * d_max)


SLIDE_FACTORS: tuple[float, ...] = tuple(1.05 * 1.12 ** k for k in range(14))
"""Distance factors λ :func:`slide_behind` tries, in order: 1.05 to 4.1, 12 % apart."""


def slide_behind(
    scene: DynamicGaussians,  # M Gaussians (deformation optional)
    index: Tensor,  # (P,) long, the Gaussians to move
    origins: Tensor,  # (P, 3) centre of each one's source camera, metres
    viewmat: Tensor,  # (4, 4) world-to-camera of the input camera
    K: Tensor,  # (3, 3) pixels
    time: float,  # clip time of the photograph, in [0, 1]
    width: int,
    height: int,
    surface_depth: Tensor,  # (H, W) z-depth of the photograph's surface at the input view, metres
    *,
    factors: tuple[float, ...] = SLIDE_FACTORS,
    depth_tolerance: float = 0.05,
) -> tuple[DynamicGaussians, Tensor]:
    """Move Gaussians back along the rays from their source cameras until they no longer cover the photograph.

    Gaussian i of ``index`` goes to o + λ·(μ − o) with scales λ·s (o: its source camera's centre, μ, s: its
    canonical mean and scales; deformation offsets kept): seen from o it keeps its direction and its angular size,
    i.e. its pixel and footprint in its source frame, while its depth there grows by λ. λ is the first of
    ``factors`` at which, deformed to ``time``, it passes :func:`occluder_mask`'s test against ``surface_depth``
    (its footprint at the input view covers no pixel whose surface it is not clearly behind); a Gaussian for which
    no factor does stays where it is and is reported. Where a generated frame and the photograph disagree about a
    surface, the photograph (observed) keeps the input view and the generated Gaussian keeps its own view, at the
    nearest depth consistent with both. Our rule (docs/DESIGN.md, "Data flow of generate").

    Returns:
        (the scene with the moved Gaussians — new tensors, differentiable in the canonical means and scales at the
        chosen λ; the input scene is not modified —, (P,) bool: True = moved, False = no factor frees it).

    Raises:
        ValueError: ``index`` and ``origins`` not (P,) and (P, 3); a factor ≤ 1; ``surface_depth`` not
            (height, width); the checks of :func:`occluder_mask`.
    """
    if index.dim() != 1 or tuple(origins.shape) != (index.shape[0], 3):
        raise ValueError(f"index (P,) and origins (P, 3) must match, got {tuple(index.shape)} and "
                         f"{tuple(origins.shape)}")
    if not factors or min(factors) <= 1.0:
        raise ValueError(f"factors must be > 1, got {factors!r}")
    width, height = check_positive_int("width", width, "pixels"), check_positive_int("height", height, "pixels")
    depth_tolerance = _check_thresholds(1.0, depth_tolerance)
    if tuple(surface_depth.shape) != (height, width):
        raise ValueError(f"surface_depth must have shape ({height}, {width}), got {tuple(surface_depth.shape)}")
    canonical = scene.canonical
    means = canonical.means
    index, origins = index.to(means.device), origins.to(means)
    viewmat, K, depth = viewmat.to(means), K.to(means), surface_depth.to(means)
    found = torch.zeros(index.shape[0], dtype=torch.bool, device=means.device)
    lam = torch.ones(index.shape[0], dtype=means.dtype, device=means.device)
    with torch.no_grad():
        g = scene.at(float(time), gate=0.0, index=index)  # the P Gaussians at the photo's time
        mu = means[index]
        offset, quats, scales, opacities = g.means - mu, g.quats, g.scales, g.opacities
        for f in factors:
            i = torch.nonzero(~found).squeeze(1)
            if i.numel() == 0:
                break
            pos = origins[i] + f * (mu[i] - origins[i]) + offset[i]
            free = i[~_covers(pos, quats[i], scales[i] * f, opacities[i], viewmat, K, width, height, depth,
                              depth_tolerance)]
            lam[free], found[free] = f, True
    moved, lam = index[found], lam[found, None].detach()
    new_means, new_scales = means.clone(), canonical.scales.clone()
    new_means[moved] = origins[found] + lam * (means[moved] - origins[found])
    new_scales[moved] = canonical.scales[moved] * lam
    slid = Gaussians(new_means, canonical.quats, new_scales, canonical.opacities, canonical.sh)
    return dataclasses.replace(scene, canonical=slid), found


def settle_generated(
    scene: DynamicGaussians,  # M Gaussians: the photo layer and backdrop (source 0), then generated frames
    source: Tensor,  # (M,) long, source frame index in [0, S)
    cameras: CameraPath,  # the clip's path at the scene's image size
    sources: Tensor,  # (S,) long, the video frame of each source frame
    surface_depth: Tensor,  # (H, W) z-depth of the photo layer at the input view, metres
    *,
    factors: tuple[float, ...] = SLIDE_FACTORS,
) -> tuple[DynamicGaussians, Tensor, dict[str, int]]:
    """Generated Gaussians made to add only what the photograph does not show (docs/DESIGN.md, "Data flow of
    generate"): near-duplicates of a surface an earlier source frame placed are dropped (:func:`duplicate_mask`);
    of the rest, those that would cover the photograph at the input view (:func:`occluder_mask` against the photo
    layer's exact ``surface_depth``) slide back along their source camera's rays until they do not
    (:func:`slide_behind` with ``factors``; ``()`` drops them all, the rule before the slide), and are dropped only
    where no factor frees them. One rule for generation and training (``training.objectives``); the ladder's cost
    and effect: ``benchmarks/slide_ladder.py``.

    Returns:
        (the scene with the slid Gaussians moved, (M,) bool on the scene's device: True = drop, never for source 0,
        counts {"duplicates", "slid", "occluders": dropped as covering the photograph}).

    Raises:
        ValueError: as :func:`duplicate_mask`, :func:`occluder_mask` and :func:`slide_behind`.
    """
    drop = torch.zeros(scene.num_gaussians, dtype=torch.bool, device=scene.canonical.means.device)
    if len(sources) < 2:
        return scene, drop, {"duplicates": 0, "slid": 0, "occluders": 0}
    source = source.to(drop.device)  # as duplicate_mask and occluder_mask: a CPU ``source`` with a CUDA scene
    W, H = cameras.width, cameras.height
    t0 = float(cameras.times[0])
    dup = duplicate_mask(scene, source, cameras.viewmats[sources], cameras.Ks[sources], cameras.times[sources], W, H)
    # Against the exact surface depth each Gaussian's test is its own: run on the whole scene (no select, which would
    # copy the deformation of nearly every Gaussian) and keep the non-duplicates.
    covers = occluder_mask(scene, source, cameras.viewmats[0], cameras.Ks[0], t0, W, H, surface_depth=surface_depth)
    occl = torch.nonzero(covers & ~dup).squeeze(1)
    moved = torch.zeros(occl.shape[0], dtype=torch.bool, device=occl.device)
    if factors:
        viewmats = cameras.viewmats[sources].to(scene.canonical.means)
        centres = -(viewmats[:, :3, :3].transpose(1, 2) @ viewmats[:, :3, 3:])[..., 0]  # (S, 3) camera centres
        scene, moved = slide_behind(scene, occl, centres[source[occl]], cameras.viewmats[0],
                                    cameras.Ks[0], t0, W, H, surface_depth, factors=factors)
    drop |= dup
    drop[occl[~moved]] = True
    return scene, drop, {"duplicates": int(dup.sum()), "slid": int(moved.sum()), "occluders": int((~moved).sum())}


def _footprint_max(depth: Tensor, u: Tensor, v: Tensor, r: Tensor) -> Tensor:
    """An upper bound of ``depth`` (H, W) over the square of half-width ``r`` around each (u, v) (P,) (pixel
    coordinates, pixel (i, j) centred at (j + 0.5, i + 0.5)), within the image; 0 where the square misses it.

    The half-widths are rounded up to a geometric ladder (at most 19 % larger) and each rung is one grey dilation
    (OpenCV's van Herk/Gil-Werman ``cv2.dilate``, O(1) per pixel whatever the square) read at the pixel nearest
    the centre inside the image (a square around it holds the part of the original square inside the image).
    """
    H, W = depth.shape
    hit = (u + r >= 0) & (u - r < W) & (v + r >= 0) & (v - r < H)
    col = u.floor().clamp(0, W - 1).long()
    row = v.floor().clamp(0, H - 1).long()
    cap = float(H + W)
    rung = torch.ceil(torch.log(r.clamp(1.0, cap)) / math.log(_RUNG)).long()  # r ≤ _RUNG**rung
    out = torch.zeros_like(u)
    host = depth.detach().cpu().numpy()  # device: cv2.dilate runs on the host; result moved back
    for k in torch.unique(rung[hit]).tolist():
        half = int(math.ceil(min(_RUNG**k, cap)))
        size = 2 * half + 1
        dilated = torch.from_numpy(cv2.dilate(host, np.ones((size, size), np.uint8), borderType=cv2.BORDER_CONSTANT,
                                              borderValue=0.0)).to(depth)
        sel = torch.nonzero(hit & (rung == k)).squeeze(1)
        out[sel] = dilated[row[sel], col[sel]].to(out.dtype)
    return out


_RUNG = 1.2
"""Ratio between successive half-widths of :func:`_footprint_max` (its over-estimate of a footprint, ≤ 20 %)."""


def _check_thresholds(min_alpha: object, depth_tolerance: object) -> float:
    """ValueError unless 0 < ``min_alpha`` ≤ 1 and ``depth_tolerance`` > 0 (finite); returns the tolerance."""
    if isinstance(min_alpha, (bool, str, bytes)) or not 0.0 < _as_float(min_alpha) <= 1.0:
        raise ValueError(f"min_alpha must lie in (0, 1], got {min_alpha!r}")
    return check_positive("depth_tolerance", depth_tolerance)


def _surface_lookup(surface, points: Tensor, viewmat: Tensor, K: Tensor, width: int, height: int,
                    min_alpha: float) -> tuple[Tensor, Tensor, Tensor]:
    """Render ``surface`` (Gaussians) from one camera ("ED": alpha A, expected depth D) and look up each of
    ``points`` (P, 3) world: its camera z, and whether it projects inside the image (z > near plane) to a
    pixel (⌊v⌋, ⌊u⌋) with A ≥ ``min_alpha``. Returns covered (P,) bool, z (P,), D at that pixel (P,)."""
    out, alpha, _ = rasterize(surface.means, surface.quats, surface.scales, surface.opacities,
                              surface.opacities[:, None], viewmat[None], K[None], width, height, render_mode="ED")
    depth, alpha = out[0, ..., 0], alpha[0, ..., 0]  # (H, W) metres, (H, W)
    p = points @ viewmat[:3, :3].T + viewmat[:3, 3]  # (P, 3) camera frame
    z = p[:, 2]
    front = z > NEAR_PLANE
    zs = torch.where(front, z, torch.ones_like(z))
    u = K[0, 0] * p[:, 0] / zs + K[0, 2]
    v = K[1, 1] * p[:, 1] / zs + K[1, 2]
    inside = front & (u >= 0) & (u < width) & (v >= 0) & (v < height)
    row = torch.where(inside, v, 0).floor().long().clamp(0, height - 1)
    col = torch.where(inside, u, 0).floor().long().clamp(0, width - 1)
    return inside & (alpha[row, col] >= min_alpha), z, depth[row, col]


def _check_sources(scene: DynamicGaussians, source: Tensor, viewmats: Tensor, Ks: Tensor, times: Tensor) -> int:
    """Shape, dtype and range checks of :func:`duplicate_mask`'s per-source arguments; returns S."""
    if viewmats.dim() != 3 or tuple(viewmats.shape[1:]) != (4, 4) or viewmats.shape[0] < 1:
        raise ValueError(f"viewmats must have shape (S, 4, 4) with S ≥ 1 source frames, got {tuple(viewmats.shape)}")
    S, M = viewmats.shape[0], scene.num_gaussians
    if tuple(Ks.shape) != (S, 3, 3):
        raise ValueError(f"Ks must have shape (S, 3, 3) = {(S, 3, 3)}, got {tuple(Ks.shape)}")
    if tuple(times.shape) != (S,):
        raise ValueError(f"times must have shape (S,) = ({S},), got {tuple(times.shape)}")
    for name, t in (("viewmats", viewmats), ("Ks", Ks), ("times", times)):
        check_finite(name, t)
    if bool(((times < 0) | (times > 1)).any()):
        raise ValueError(f"times must lie in [0, 1], got {times.tolist()}")
    if tuple(source.shape) != (M,):
        raise ValueError(f"source must have shape (M,) = ({M},) (one per Gaussian), got {tuple(source.shape)}")
    if source.is_floating_point() or source.is_complex() or source.dtype == torch.bool:
        raise ValueError(f"source must be an integer tensor, got dtype {source.dtype}")
    if M and (int(source.min()) < 0 or int(source.max()) >= S):
        lo, hi = int(source.min()), int(source.max())
        raise ValueError(f"source must lie in [0, S) = [0, {S}), got values in [{lo}, {hi}]")
    return S


def _as_float(value: object) -> float:
    """``float(value)``, or NaN (fails every range check) when it is not a number."""
    try:
        return float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return math.nan


def settle_and_prune(scene: DynamicGaussians, source: Tensor, cameras: CameraPath, sources: Tensor,
                     surface_depth: Tensor, photo_gaussians: int, min_opacity: float
                     ) -> tuple[DynamicGaussians, Tensor, dict[str, int]]:
    """Settle and prune an assembled scene (docs/DESIGN.md, "Data flow of generate", step 8): :func:`settle_generated`,
    then :func:`prune_mask` of everything after the first ``photo_gaussians`` (the photo layer is opaque and
    pixel-aligned to the first camera, seen by construction).

    Args:
        scene: M Gaussians, the photo layer first.  source: (M,) long, each one's source frame index in [0, S).
        cameras: the clip's path at the scene's image size.  sources: (S,) long, the video frame of each source frame.
        surface_depth: (H, W) the photo layer's z-depth at the input view, metres.
        photo_gaussians: the photo layer's count.  min_opacity: :func:`prune_mask`'s threshold.

    Returns:
        (the kept scene, (M',) long index of each kept Gaussian in ``scene``, counts of :func:`prune_mask` and
        :func:`settle_generated` with "before" the whole scene).

    Raises:
        ValueError: the camera path sees none of the scene (every Gaussian pruned); as :func:`settle_generated`.
    """
    dev = scene.canonical.means.device
    index = torch.arange(scene.num_gaussians, device=dev)
    scene, drop, settled = settle_generated(scene, source, cameras, sources, surface_depth)
    keep = ~drop  # one select of the whole scene (and its deformation) at the end, not one per step
    generated = keep & (index >= photo_gaussians)
    keep[generated], stats = prune_mask(scene.select(generated), cameras, min_opacity=min_opacity)
    stats = {**stats, "before": int((~drop).sum()), "after": int(keep.sum())}
    scene, index = scene.select(keep), index[keep]
    stats = {**stats, "before": stats["before"] + settled["duplicates"] + settled["occluders"], **settled}
    if stats["after"] == 0:
        raise ValueError(nothing_seen_message(stats, min_opacity))
    return scene, index, stats
