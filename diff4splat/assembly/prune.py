"""Pruning of Gaussians: those no camera of a path sees, near-duplicates across source frames, and generated
Gaussians that would cover the photograph (docs/DESIGN.md, "Data flow of generate", step 8; our rules, not the
paper's)."""
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
    """(M,) bool: which Gaussians any camera of ``cameras`` sees at its own frame time, i.e. passes the renderer's
    culling (:func:`diff4splat.render.project_gaussians`) and, with temporal support, the gate of
    :meth:`DynamicGaussians.active_indices`."""
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
    """The Gaussians :func:`prune_scene` keeps: opacity ≥ ``min_opacity`` (in [0, 1)) and seen by a camera of
    ``cameras`` (None: opacity only).

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
    """The error message when pruning left no Gaussian (``stats`` of :func:`prune_mask`), naming the likely cause."""
    msg = (f"the camera path sees none of the scene: all {stats['before']} Gaussians were pruned "
           f"({stats['unseen']} outside every camera's view, {stats['low_opacity']} with opacity < {min_opacity})")
    if stats["unseen"] == 0:
        return msg + "; likely cause: the model's weights (every Gaussian is transparent)"
    return msg + ("; likely cause: the cameras look away from the scene (the scene lies in front of the "
                  "first camera, along its +z axis, OpenCV axes)")


def prune_scene(scene: DynamicGaussians, cameras: CameraPath | None = None, min_opacity: float = 0.005,
                near_plane: float = NEAR_PLANE) -> tuple[DynamicGaussians, dict[str, int]]:
    """Drop the Gaussians :func:`prune_mask` does not keep; returns the pruned scene and its counts.

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
    """(M,) bool, True where a Gaussian of a later source frame re-describes a surface an earlier one already placed.

    For s = 1 … S−1 in order, the not-yet-dropped Gaussians of frames < s are rendered at ``times[s]`` from camera s
    (alpha A, expected depth D); a Gaussian of frame s whose deformed mean projects in front of the near plane to a
    pixel with A ≥ ``min_alpha`` (in (0, 1]) and |z − D| ≤ ``depth_tolerance``·D (> 0) is a duplicate. Frame 0 never
    is. ``width``, ``height``: image size, pixels (≥ 1).

    Raises:
        ValueError: wrong shapes, a non-integer ``source`` or one outside [0, S), non-finite cameras or times, times
            outside [0, 1], width/height < 1, ``min_alpha`` outside (0, 1], ``depth_tolerance`` not finite and > 0.
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
    """Which Gaussians of later source frames would cover the photograph at the input view (True = drop, never for
    source 0).

    A candidate deformed to ``time`` is dropped when the square around its projected centre (half-width 10/9 of the
    renderer's 3σ radius + 1 pixel) holds a pixel covered by source 0 (alpha ≥ ``min_alpha``) whose depth D it is not
    clearly behind: z < (1 + ``depth_tolerance``)·D. The largest D over the square comes from a grey dilation
    (:func:`_footprint_max`), so the test is conservative; culled Gaussians are kept. ``surface_depth``, when given,
    is used instead of rendering source 0.

    Raises:
        ValueError: the checks of :func:`duplicate_mask` (one camera); ``surface_depth`` not (height, width).
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
    """:func:`occluder_mask`'s footprint test of P Gaussians against ``depth`` (H, W; 0 = uncovered): (P,) bool."""
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

    Gaussian i of ``index`` goes to o + λ·(μ − o) with scales λ·s (o its source camera's centre; deformation offsets
    kept), so its pixel and footprint in its source frame are unchanged; λ is the first of ``factors`` at which it
    passes :func:`occluder_mask`'s test against ``surface_depth`` at ``time``. One no factor frees stays put.

    Returns:
        (the scene with the moved Gaussians, new tensors differentiable in the canonical means and scales,
        (P,) bool: True = moved).

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
    """Generated Gaussians made to add only what the photograph does not show: :func:`duplicate_mask`, then those of the
    rest that cover the photograph (:func:`occluder_mask` against ``surface_depth``) slide back (:func:`slide_behind`;
    ``factors=()`` drops them) and are dropped only where no factor frees them. The same rule serves training.

    Returns:
        (the scene with the slid Gaussians moved, (M,) bool: True = drop, never for source 0,
        counts {"duplicates", "slid", "occluders"}).

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
    """Upper bound of ``depth`` (H, W) over the square of half-width ``r`` around each (u, v) (P,); 0 off the image."""
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
    """(covered, camera z, D) (P,) of ``points`` (P, 3) against ``surface`` rendered from one camera (depth D)."""
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
    then :func:`prune_mask` (``min_opacity``) of everything after the photo layer's first ``photo_gaussians``.
    ``source``: (M,) each Gaussian's source frame; ``sources``: (S,) the video frame of each source frame;
    ``surface_depth``: (H, W) the photo layer's z-depth, metres.

    Returns:
        (the kept scene, (M',) long index of each kept Gaussian in ``scene``, the counts of :func:`prune_mask` and
        :func:`settle_generated`).

    Raises:
        ValueError: the camera path sees none of the scene; as :func:`settle_generated`.
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
